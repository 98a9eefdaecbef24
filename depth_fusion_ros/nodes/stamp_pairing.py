"""Pairs the parts of one keyframe that arrive on separate topics by their exact header stamp.

Every upstream stream is in stamp order, so a pending keyframe still missing a part whose
stream has already passed its stamp will never get it and is dropped at once (``unpaired``);
the others wait at most ``timeout`` seconds (``pair_timeout``) and at most ``max_pending``
keyframes wait (``pair_overflow``). Stragglers of a closed keyframe are counted
(``late_part``). A part whose stamps jump back by ``restart_after`` seconds begins a new stream
(a bag played again): accepted, the closed stamps forgotten, and a pending keyframe whose stamp
the new stream reuses is replaced (``stream_restart``). Memory stays bounded whatever the
input. No ROS import: callers pass the message header.

Not every stamp is a keyframe's. A single-view node reading a raw camera publishes a depth for
every image, and only the images the multi-view node chose get its parts (``keyframe_parts``).
A pending stamp that holds none of those parts when one of their streams passes it was not
chosen: it is closed without a drop and counted in ``not_keyframes``. A stamp that holds any
of them is a keyframe, and missing the rest is a drop as before.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..data import messages
from .input_error import InputError
from .stamp_guard import StampGuard

#: How many closed keyframe stamps are remembered to recognise late parts.
CLOSED_MEMORY = 256


@dataclass
class Pairing:
    """The parts of one keyframe received so far."""

    stamp_ns: int
    first_seen: float
    header: Any
    parts: dict[str, Any] = field(default_factory=dict)


class StampPairer:
    """Collects required (and optional) parts per stamp; hands complete keyframes on."""

    def __init__(
        self,
        required: Sequence[str],
        optional: Sequence[str],
        timeout: float,
        max_pending: int,
        on_complete: Callable[[Pairing], None],
        on_drop: Callable[[str, str], None],
        restart_after: float = 0.0,
        on_restart: Callable[[str, int], None] | None = None,
        on_dropped_keyframe: Callable[[int, str], None] | None = None,
        keyframe_parts: Sequence[str] = (),
    ) -> None:
        self.required = tuple(required)
        #: parts only a chosen keyframe gets (the multi-view node's); see the module docstring
        self.keyframe_parts = frozenset(keyframe_parts)
        #: stamps closed as not a keyframe's (passed by a keyframe part's stream, holding none)
        self.not_keyframes = 0
        self.known = set(required) | set(optional)
        self.timeout = timeout
        self.max_pending = max_pending
        self.on_complete = on_complete
        self.on_drop = on_drop
        self.pending: dict[int, Pairing] = {}
        self._closed: OrderedDict[int, None] = OrderedDict()
        #: one stamp guard per part: order, duplicates, and a jump back of ``restart_after`` s
        #: taken for a new stream (0: never)
        self._guards = {part: StampGuard(part, restart_after) for part in self.known}
        self.on_restart = on_restart
        #: told ``(stamp_ns, reason)`` of every keyframe given up (a graph runner's bookkeeping)
        self.on_dropped_keyframe = on_dropped_keyframe
        self._lock = threading.Lock()

    def add(self, header: Any, part: str, value: Any) -> None:
        """Add ``part`` of the keyframe stamped ``header.stamp``."""
        if part not in self.known:
            raise ValueError(f'unknown part {part!r}')
        stamp_ns = messages.stamp_to_ns(header.stamp)
        complete = None
        with self._lock:
            try:
                restarted = self._guards[part].check(stamp_ns)
            except InputError as exc:
                self.on_drop(exc.reason, str(exc))
                return
            if restarted:  # the closed stamps were the previous stream's: the new one reuses them
                self._closed.clear()
            if stamp_ns in self._closed:
                if part in self.required:
                    self.on_drop(
                        'late_part', f'{part} of keyframe {messages.ns_to_sec(stamp_ns):.3f} came too late'
                    )
                return
            if part in self.required:
                self._drop_passed(part, stamp_ns)
            pairing = self.pending.get(stamp_ns)
            if pairing is not None and part in pairing.parts:  # a new stream reuses an old stamp
                self._close(stamp_ns, 'stream_restart', 'replaced by a new stream with the same stamp')
                pairing = None
            if pairing is None:
                pairing = self.pending[stamp_ns] = Pairing(stamp_ns, time.monotonic(), header)
                while len(self.pending) > self.max_pending:
                    self._close(min(self.pending), 'pair_overflow', 'dropped: too many keyframes waiting')
            pairing.parts[part] = value
            if all(k in pairing.parts for k in self.required):
                complete = self._close(stamp_ns)
        if complete is not None:
            self.on_complete(complete)
        if restarted and self.on_restart is not None:
            self.on_restart(part, stamp_ns)

    def expire(self, now: float) -> None:
        """Drop the keyframes that waited longer than ``timeout``."""
        with self._lock:
            for stamp_ns in [s for s, p in self.pending.items() if now - p.first_seen > self.timeout]:
                self._close(stamp_ns, 'pair_timeout', f'waited {self.timeout:g} s')

    def _drop_passed(self, part: str, stamp_ns: int) -> None:
        for old in sorted(s for s, p in self.pending.items() if s < stamp_ns and part not in p.parts):
            if part in self.keyframe_parts and self.keyframe_parts.isdisjoint(self.pending[old].parts):
                self._close(old)  # an image the multi-view node did not choose: nothing lost
                self.not_keyframes += 1
                continue
            self._close(old, 'unpaired', f'will not get its {part}')

    def _close(self, stamp_ns: int, reason: str = '', message: str = '') -> Pairing:
        pairing = self.pending.pop(stamp_ns)
        self._closed[stamp_ns] = None
        while len(self._closed) > CLOSED_MEMORY:
            self._closed.popitem(last=False)
        if reason:
            missing = ', '.join(k for k in self.required if k not in pairing.parts) or 'nothing'
            self.on_drop(
                reason,
                f'keyframe {messages.ns_to_sec(stamp_ns):.3f} {message}: missing {missing}',
            )
            if self.on_dropped_keyframe is not None:
                self.on_dropped_keyframe(stamp_ns, reason)
        return pairing
