"""The calibration checks' own process, seen from ``multi_view_node`` (the child:
``check_process_main.py``, where it says why a process).

One process serves the node's three check runners (``check_runner.py``). A runner's thread
keeps its queue, its wait for the keyframe path and its ``pending`` count; it hands each item
to the process and waits on the pipe for the reply, holding no GIL meanwhile. The three threads
take turns on the pipe (a lock): the process runs one check's item at a time, as one core at a
lower priority should.

The node starts the process as it starts (:meth:`CheckProcess.start`; a node whose checks are
all off starts none), so the process has imported the checks' code before the stream comes:
started with a check's first sample, it made the time offset check's correction 1-3
keyframes later in a paced replay (docs/performance.md, "The calibration checks in a process of their
own"). Its start costs the node nothing: the child imports at its own priority.

Faults: a process that cannot start or dies (killed, out of memory) is said once through
``on_lost``; every later call raises :class:`CheckProcessLostError` at once, and the runners go on
checking on their own threads (``CheckRunner``), from the next frame.
"""

from __future__ import annotations

import contextlib
import itertools
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from multiprocessing.connection import Connection

from ..child_process import child_environment, receive, send
from .params import ParamSpec

#: The checks' niceness by default: below the nodes, above the adaptation's training
#: (``SCHED_IDLE``), so a check that a stream's first keyframes wait on is done before the
#: network trains on them.
DEFAULT_NICE = 10


CHECK_PROCESS_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'calibration_checks.process',
        True,
        'run the focal length, time offset and mount checks in one process of their own (true) or '
        "on threads of this one (false): in a process their Python work never holds this node's GIL, "
        'so at a lower priority they only take the CPU the keyframes leave',
    ),
    ParamSpec(
        'calibration_checks.nice',
        DEFAULT_NICE,
        "scheduling niceness of the checks' process (Linux): below the nodes, above the adaptation's "
        'training (SCHED_IDLE), so the checks a stream starts with are done first; 0 = the same '
        'priority as the nodes',
        0,
        19,
    ),
)


class CheckProcessLostError(RuntimeError):
    """The checks' process is gone (or never started): the runners check on their own threads."""


class CheckProcess:
    """The parent's end of the checks' process (see module)."""

    def __init__(self, nice: int = DEFAULT_NICE, on_lost: Callable[[str], None] | None = None):
        self.nice = int(nice)
        self._on_lost = on_lost
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        #: Why the process is gone (``None``: running, or not started yet).
        self.lost: str | None = None
        self._closed = False
        self._keys = itertools.count()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def key(self, name: str) -> str:
        """A key for a new check (one per check made; a restarted check gets a new one)."""
        return f'{name}:{next(self._keys)}'

    def start(self) -> None:
        """Start the process now (else the first check's item starts it)."""
        with self._lock, contextlib.suppress(CheckProcessLostError):
            if self._conn is None and self.lost is None and not self._closed:
                self._start()

    def make(self, key: str, cls: type, args: tuple) -> None:
        """Make the check ``cls(*args)`` in the process under ``key`` (started here if need be)."""
        with self._lock:
            self._send(('make', key, cls, args))

    def feed(self, key: str, method: str, args: tuple) -> tuple:
        """``check.method(*args)`` in the process: ``('fed', result, early, collected, cpu)`` or
        ``('error', text, cpu)`` (see ``check_process_main.py``)."""
        with self._lock:
            self._send(('feed', key, method, args))
            try:
                return receive(self._conn)
            except (EOFError, OSError) as exc:
                raise self._lose(f'it ended while checking ({type(exc).__name__})') from None

    def drop(self, key: str) -> None:
        """Forget the check ``key`` (its runner stopped); nothing when the process is gone."""
        if self.lost is not None or self._conn is None:
            return
        with self._lock, contextlib.suppress(CheckProcessLostError):
            self._send(('drop', key))

    def close(self, timeout: float = 2.0) -> None:
        """End the process (it holds nothing worth keeping): a runner's thread still waiting on
        it gets :class:`CheckProcessLostError` and ends, as its runner is closing."""
        self._closed = True
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout)
        if self._conn is not None and self._lock.acquire(timeout=timeout):
            try:
                self._conn.close()
            finally:
                self._lock.release()

    def _send(self, message: tuple) -> None:
        """Send under the lock, starting the process first if need be."""
        if self.lost is not None:
            raise CheckProcessLostError(self.lost)
        if self._closed:
            raise CheckProcessLostError('closed')
        if self._conn is None:
            self._start()
        try:
            send(self._conn, message)
        except OSError as exc:
            raise self._lose(f'its pipe closed ({type(exc).__name__})') from None

    def _start(self) -> None:
        ours, theirs = socket.socketpair()
        command = [sys.executable, '-m', 'depth_fusion_ros.nodes.check_process_main']
        try:
            self._proc = subprocess.Popen(
                [*command, str(theirs.fileno()), str(self.nice)],
                pass_fds=(theirs.fileno(),),
                env=child_environment(),
            )
        except OSError as exc:
            ours.close()
            raise self._lose(f'it could not start ({type(exc).__name__}: {exc})') from None
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())

    def _lose(self, why: str) -> CheckProcessLostError:
        """Mark the process gone (said once, unless the node is closing); the error to raise."""
        if self.lost is None:
            self.lost = why
            if not self._closed and self._on_lost is not None:
                self._on_lost(why)
        return CheckProcessLostError(why)
