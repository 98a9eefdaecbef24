"""The calibration checks' own process: the child side of :class:`.check_process.CheckProcess`.

Why a process: a check's features, matching and fits are Python and numpy work that holds the
GIL. On a thread of ``multi_view_node`` it holds up the node's filter and callbacks, and
a lower priority cannot help there: a niced thread that holds the GIL when the kernel
deschedules it holds everyone up (docs/performance.md, "The calibration checks yield to the
keyframes" and "A slower machine"). A process has its own interpreter, so its niceness only
says who gets the CPU.

Started as ``python -m depth_fusion_ros.nodes.check_process_main FD NICE`` (not by
``multiprocessing``, whose spawn re-imports the parent's main script: a node's, with rclpy and
torch), as the adaptation's training process is. This module imports only the standard
library at the top; the child lowers its priority, then imports the checks' code (numpy,
OpenCV, scipy; neither torch nor rclpy) at once, one thread each.

Protocol over the connection on ``FD`` (``multiprocessing.connection``, pickled tuples), one
request at a time from the parent's runner threads (their lock):

* ``('make', key, cls, args)``: a check ``cls(*args)`` under ``key``; no reply (a check that
  cannot be made says so at its first feed);
* ``('feed', key, method, args)`` -> ``('fed', result, early, collected, cpu)``, ``result``
  what ``check.method(*args)`` returned, ``early`` the focal check's early look (``None``
  elsewhere), ``collected`` the pairs it holds, ``cpu`` the call's CPU seconds; or
  ``('error', text, cpu)`` when the call raised;
* ``('drop', key)``: the check is forgotten; no reply.

The parent's end closing (the node gone, or it killed this process) ends it.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

from ..child_process import receive, send
from ..priority import lower_priority


def pairs_held(check: Any) -> int:
    """The pairs a check holds: a list of pairs (the paired checks) or their count (the time
    offset check)."""
    pairs = getattr(check, 'pairs', 0)
    return len(pairs) if isinstance(pairs, list) else int(pairs)


class _Unmade:
    """A check whose constructor raised: every feed raises its error again."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __getattr__(self, name: str) -> Any:
        raise RuntimeError(f'the check could not be made: {self.text}')


def _make(cls: type, args: tuple) -> Any:
    try:
        return cls(*args)
    except Exception as exc:
        return _Unmade(f'{type(exc).__name__}: {exc}')


def _feed(check: Any, method: str, args: tuple) -> tuple:
    started = time.thread_time()
    try:
        result = getattr(check, method)(*args)
    except Exception as exc:  # the parent's runner raises it on its thread, as a local check would
        return ('error', f'{type(exc).__name__}: {exc}', time.thread_time() - started)
    cpu = time.thread_time() - started
    return ('fed', result, getattr(check, 'early', None), pairs_held(check), cpu)


def serve(conn: Connection) -> None:
    """Answer the parent until its end closes."""
    checks: dict[str, Any] = {}
    while True:
        request = receive(conn)
        kind = request[0]
        if kind == 'make':
            checks[request[1]] = _make(request[2], request[3])
        elif kind == 'feed':
            _, key, method, args = request
            check = checks.get(key)
            if check is None:
                send(conn, ('error', f'no check {key!r} was made', 0.0))
            else:
                send(conn, _feed(check, method, args))
        elif kind == 'drop':
            checks.pop(request[1], None)


def _warm_up() -> None:
    """One thread for numpy's BLAS and OpenCV (the child stays on one core, whatever it does),
    and the checks' code imported now, while the node waits for its stream: a check's first
    sample then finds the process ready (imported at the first one, the time offset check's
    correction came 1-3 keyframes later in a paced replay)."""
    for name in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ[name] = '1'
    import cv2

    cv2.setNumThreads(1)
    # What the checks import where first used (so that a node imports them only once ready):
    # in a fresh process they cost a check's first sample more than its own work.
    import scipy.optimize
    import scipy.spatial.transform  # noqa: F401

    from ..multiview import focal_check, mount_check, time_offset_check  # noqa: F401


def main(argv: list[str]) -> int:
    fd, nice = (int(a) for a in argv)
    lower_priority(nice)
    # Ctrl+C to the process group is the node's to handle; it ends this process as it shuts
    # down, and a node that dies closes the pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _warm_up()
    conn = Connection(fd)
    try:
        serve(conn)
    except (EOFError, OSError):  # the parent is gone (its end of the pipe closed)
        return 0
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
