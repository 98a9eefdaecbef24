"""One stream's stamps in order: a repeat or a step back is refused, a large jump back is a new stream."""

from __future__ import annotations

import time

from ..data import messages
from .input_error import InputError


class StampGuard:
    """Rejects stamps that repeat or go backwards on one stream (a replay glitch, a bad driver),
    and takes a large backward jump for what it is: a new stream.

    A bag played again, a looped bag or a client restarted with the same sequence starts over
    at stamps the node has passed; without this every message of it would be dropped as out
    of order. A jump back of at least ``restart_after`` seconds is accepted and reported by
    :meth:`check` (``True``), as tf2 clears its buffer when time jumps back. Two streams
    interleaved on one topic would jump back and forth: after ``MAX_RESTARTS`` restarts within
    ``RESTART_WINDOW`` seconds (wall time) the guard drops again, and the input watch names
    the mix.
    """

    MAX_RESTARTS = 3
    RESTART_WINDOW = 10.0

    def __init__(self, stream: str, restart_after: float = 0.0) -> None:
        self.stream = stream
        self.restart_after = float(restart_after)
        self.last_ns: int | None = None
        #: wall times (monotonic s) of the recent restarts, for the interleaving limit
        self._restarts: list[float] = []

    def check(self, stamp_ns: int) -> bool:
        """Raise ``InputError`` for a duplicate or older stamp; otherwise remember ``stamp_ns``.

        Returns ``True`` when ``stamp_ns`` begins a new stream (a jump back of at least
        ``restart_after`` s, ``> 0``): the caller starts over.
        """
        restarted = False
        if self.last_ns is not None:
            if stamp_ns == self.last_ns:
                raise InputError(
                    f'duplicate_stamp_{self.stream}',
                    f'{self.stream} stamp {messages.ns_to_sec(stamp_ns):.6f} repeats the previous one',
                )
            if stamp_ns < self.last_ns:
                restarted = self._restart_allowed(stamp_ns)
                if not restarted:
                    raise InputError(
                        f'stamp_out_of_order_{self.stream}',
                        f'{self.stream} stamp {messages.ns_to_sec(stamp_ns):.6f} is older than the '
                        f'previous {messages.ns_to_sec(self.last_ns):.6f}',
                    )
        self.last_ns = stamp_ns
        return restarted

    def _restart_allowed(self, stamp_ns: int) -> bool:
        assert self.last_ns is not None
        jump = messages.ns_to_sec(self.last_ns - stamp_ns)
        if self.restart_after <= 0 or jump < self.restart_after:
            return False
        now = time.monotonic()
        self._restarts = [t for t in self._restarts if now - t < self.RESTART_WINDOW]
        if len(self._restarts) >= self.MAX_RESTARTS:
            return False
        self._restarts.append(now)
        return True

    def reset(self) -> None:
        self.last_ns = None
