"""Lowering a background process's CPU priority (standard library only: a child calls it first
thing, before it imports torch).

Two background processes use it: the adaptation's training process
(``adaptation/trainer_process.py``) and the fusion kernels' builder
(``fusion/aot_background.py``). Each asks for a niceness *and* ``SCHED_IDLE``: under the EEVDF
scheduler of Linux 6.6 and later a niced process that runs keeps its core for its time slice
when a node's thread wakes, and the graph's keyframes pass through many such wake-ups (DDS
messages, worker queues); a ``SCHED_IDLE`` one gives the core up at once.
"""

from __future__ import annotations

import contextlib
import os


def lower_priority(nice: int) -> None:
    """Add ``nice`` to this process's niceness (quietly nothing where not permitted)."""
    if nice > 0:
        with contextlib.suppress(AttributeError, OSError):
            os.nice(nice)


def idle_policy() -> str:
    """Run this process under ``SCHED_IDLE`` (Linux): only on a core that no other task wants,
    and a waking task of any node takes the core from it at once. Returns '' or why it could
    not (another system, a kernel that refuses).

    Why, besides the niceness: under the EEVDF scheduler (Linux 6.6 and later) a niced process
    that runs keeps its core for its time slice when a node's thread wakes; the graph's
    keyframes pass through many such wake-ups (DDS messages, worker queues). On 2 cores the
    graph fused 7.50 keyframes/s flat out beside a trainer at nice +10 and 7.96 beside one
    under SCHED_IDLE (means of eleven alternated pairs), and a niced process that only spins
    slowed it as much (docs/performance.md, "Where the cores go, and the training process at
    idle priority")."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError) as exc:
        return f'{type(exc).__name__}: {exc}'
    return ''
