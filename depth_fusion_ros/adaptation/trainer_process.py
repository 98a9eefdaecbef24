"""The training side of :class:`~.remote_adapter.RemoteAdapter`: an Adapter in a process of its own.

Why a process: in one process every thread shares one GIL. The training thread is niced so
that inference, multi-view and fusion get the CPU first, but a niced thread that holds the
GIL when the kernel deschedules it holds every other thread up with it (docs/performance.md,
"Composed in real time": the composed graph fused 8-11 of 19 keyframes in real time with the
adaptation on, 14-19 with it off, though training used under a tenth of the CPU). A process
has its own interpreter: its niceness then only says who gets the CPU, and its imports (1.7 s
of ``torch._dynamo`` for the optimiser) hold up nobody.

Started as ``python -m depth_fusion_ros.adaptation.trainer_process FD NICE THREADS IDLE`` (not by
``multiprocessing``, whose spawn re-imports the parent's main script: a node's, with rclpy
and torch, before the child could lower its priority). So this module imports only the
standard library at the top, and the child is niced (and, with IDLE 1, put under
``SCHED_IDLE``: ``priority.idle_policy``) before it imports torch.

Protocol over the connection on ``FD`` (``multiprocessing.connection``: pickled tuples), one
request at a time:

* ``('init', spec, config, device)`` -> ``('ready',)`` or ``('error', text)``;
* ``('observe', sample, behind)`` -> ``('report', report, counters, weights)``, ``weights`` the
  accepted network's tensors (``state_dict`` order) after an ``updated`` report, else None;
  or ``('failed', text, counters)`` when the update raised;
* ``('restart', key, reason)`` -> ``('report', report, counters, None)``: the adapter
  started over from the loaded weights (``Adapter.restart``), which the parent holds too;
* ``('stop',)``, or the parent's end closing: the child returns; one that comes during an
  update stops the update first, as an abort does;
* ``('abort',)`` while an update runs asks it to stop: between its steps the adapter looks at
  the pipe (:class:`_Requests`), restores the weights and reports the keyframe ``stopped``. An
  abort that comes after the update ended is skipped as the next request is read.

Why a message and not a signal (as before): a signal carries no request. One sent right after
a request could reach this process before it had cleared the previous request's flag, and the
update then ran in full (the likely cause of one test failure with two test workers on two
cores). An abort on the pipe sits after the request it is for, so it can neither come early
nor stop the next update.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
from multiprocessing.connection import Connection
from typing import Any

from ..child_process import receive, send
from ..priority import idle_policy, lower_priority


class _Requests:
    """What the parent asks while an update runs, read from the pipe between the adapter's
    steps: an ``abort`` of the update in hand, a ``stop`` (close) or the pipe's end, both of
    which stop the update too."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.abort = False
        self.stop = False

    def check(self) -> bool:
        while not self.stop and self.conn.poll(0):
            try:
                kind = receive(self.conn)[0]
            except (EOFError, OSError):  # the parent is gone
                kind = 'stop'
            self.abort = True
            self.stop = kind == 'stop'
        return self.abort


def main(argv: list[str]) -> int:
    fd, nice, threads, idle = (int(a) for a in argv)
    lower_priority(nice)
    not_idle = idle_policy() if idle else ''
    # The adapter's warnings (a rolled-back update) reach the node's terminal, named as this
    # process's; the node counts and logs each report itself as well.
    logging.basicConfig(
        level=logging.WARNING, format=f'[adaptation trainer {os.getpid()}] %(levelname)s %(message)s'
    )
    if not_idle:
        log = logging.getLogger(__name__)
        log.warning('SCHED_IDLE not set (%s): training at nice +%d only', not_idle, nice)
    # Ctrl+C or a SIGTERM to the process group is the parent's to handle: it stops this child
    # (and the update in hand) as it shuts down, and a parent that dies closes the pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    conn = Connection(fd)
    try:
        adapter = _build(conn, threads)
    except (EOFError, OSError):
        return 0
    if adapter is None:
        return 1
    _serve(conn, adapter)
    return 0


def _build(conn: Connection, threads: int) -> Any:
    _, spec, config, device = receive(conn)
    try:
        import torch

        if threads > 0:
            torch.set_num_threads(threads)
        from .adapter import Adapter

        adapter = Adapter.from_spec(spec, config, device)
        adapter.warm_up()
    except Exception as exc:  # the parent logs it once and trains no more (inference goes on)
        send(conn, ('error', f'{type(exc).__name__}: {exc}'))
        return None
    send(conn, ('ready',))
    return adapter


def _serve(conn: Connection, adapter: Any) -> None:
    try:
        _loop(conn, adapter)
    except (EOFError, OSError):  # the parent is gone (its end of the pipe closed)
        return


def _loop(conn: Connection, adapter: Any) -> None:
    while True:
        request = receive(conn)
        if request[0] == 'stop':
            return
        if request[0] == 'abort':  # for an update that had ended before it came
            continue
        if request[0] == 'restart':
            report = adapter.restart(request[1], request[2])
            send(conn, ('report', report, adapter.counters, None))
            continue
        _, sample, behind = request
        asked = _Requests(conn)
        try:
            report = adapter.observe(sample, abort=asked.check, behind=behind)
        except Exception as exc:  # a bad sample must not end adaptation (the parent counts it)
            send(conn, ('failed', f'{type(exc).__name__}: {exc}', adapter.counters))
        else:
            weights = _weights(adapter) if report.status == 'updated' else None
            send(conn, ('report', report, adapter.counters, weights))
        if asked.stop:
            return


def _weights(adapter: Any) -> list[Any]:
    """The adapter's network's tensors, ``state_dict`` order, on the CPU (for the pipe)."""
    return [t.detach().cpu() for t in adapter.net.state_dict().values()]


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
