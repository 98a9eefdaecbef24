"""Torch threads of a node process started on its own (console script, launch file).

torch gives every process one thread per core. The graph is three such processes (four with
the map) on the same cores, and each of them runs many small ops: on 2 cores, three 2-thread
pools wait for each other's descheduled workers at every op. Measured live (an independent
client, 7-Scenes raw images at 30 Hz, the three console scripts started as the README shows):
13 and 20 of 29 keyframes fused without ``OMP_NUM_THREADS``, 28-29 with one thread per node.
So a node started on its own takes the share ``depth-fusion run --processes`` gives its
children: the usable cores divided by the graph's three processes, at least one. An
``OMP_NUM_THREADS`` you set wins.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

#: The processes of the graph that share the cores (multi-view, single-view, fusion).
GRAPH_PROCESSES = 3


def usable_cores() -> int:
    """Cores this process may run on (its affinity mask: a container's or taskset's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def node_threads(env: Mapping[str, str] | None = None) -> int | None:
    """Torch threads for a node process: ``None`` when ``OMP_NUM_THREADS`` is set (torch
    follows it), else the usable cores over :data:`GRAPH_PROCESSES`, at least 1."""
    env = os.environ if env is None else env
    if env.get('OMP_NUM_THREADS'):
        return None
    return max(1, usable_cores() // GRAPH_PROCESSES)


def _omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` as a thread count (``None``: unset or not a positive integer)."""
    try:
        value = int(os.environ.get('OMP_NUM_THREADS', ''))
    except ValueError:
        return None
    return value if value > 0 else None


def apply_node_threads() -> str:
    """Set the torch threads of this node process (:func:`node_threads`), and OpenCV's to the
    same share (its own pool otherwise starts one thread per core and waits for each at every
    call: colour conversion, resizing, the window sums); the line to log."""
    threads = node_threads()
    import cv2
    import torch

    # OMP_NUM_THREADS is applied too, not left to torch: torch read it when it was imported,
    # which for a node forked from the launcher's fork server (graph/forked.py) was before
    # this environment was set.
    wanted = threads if threads is not None else _omp_threads()
    if wanted is not None:
        torch.set_num_threads(wanted)
    cv2.setNumThreads(torch.get_num_threads())
    if threads is None:
        return f'torch and OpenCV threads: {torch.get_num_threads()} (OMP_NUM_THREADS)'
    return (
        f'torch and OpenCV threads: {threads} (usable cores {usable_cores()} / {GRAPH_PROCESSES} node '
        'processes; set OMP_NUM_THREADS to choose)'
    )
