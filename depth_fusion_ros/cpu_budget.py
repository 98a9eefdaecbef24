"""Where the cores go: CPU time of each node-graph process per fused keyframe.

A run's rate says how fast the graph is, not what holds it there. On a small machine the
answer is a budget: each process's CPU seconds per fused keyframe, and how many of the cores
they used together. A process that is the limit shows as the largest share; a graph whose
processes together use less than the cores waits on something else (pacing, a queue).
``depth-fusion bench`` reads it over the second half of a run (the window of "fused kf per
second of the second half"); ``depth-fusion run`` prints it for the whole playback
(:func:`budget_line`).

Read from Linux ``/proc/PID/stat`` (user + system time, in clock ticks, usually 10 ms) each
time the run reports progress, and interpolated to the window's ends. A node's own process and
its descendants are apart: the single-view node's training process runs at idle priority
(``adaptation.idle_policy``) on what the others leave, and the multi-view node's calibration
checks run in a process of their own (``calibration_checks.process``). Where ``/proc`` cannot be read (not
Linux) there are no figures, and nothing is printed.
"""

from __future__ import annotations

import itertools
import math
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path

#: How a process's descendants are named: after it, with this (the single-view node's are its
#: training process).
CHILDREN = "'s child processes"
#: What a node's child processes are, by the node (``child_role``): the single-view node's
#: training runs at idle priority, so its CPU is what the nodes left, not their cost.
TRAINING = 'the training, at idle priority'
CHECKS = 'the calibration checks'
CHILD_ROLES = {'single_view': TRAINING, 'multi_view': CHECKS, 'graph': f'{TRAINING}; {CHECKS}'}
#: Clock ticks per second of ``/proc/PID/stat``'s times.
TICKS = os.sysconf('SC_CLK_TCK') if hasattr(os, 'sysconf') else 100
#: Seconds between two walks of each process's tree (:func:`descendants`); the descendants
#: found are read at every sample in between. A walk reads the children file of every thread
#: of every graph process (a node holds dozens of DDS and torch threads): walked at every
#: progress call (0.5 s), by the CPU budget once and by the bench's memory sampler twice for
#: each process, it was the largest part of the runner's own CPU in a flat-out run (py-spy,
#: docs/performance.md "The replayer's executor"). A process born in between is read from the
#: next walk on, with all its CPU since it started.
TREE_REFRESH_S = 5.0


def child_role(name: str) -> str:
    """What a budget line's child processes are ('' for a node's own process, or a node with no
    such child): the single-view node's training, the multi-view node's calibration checks
    (``calibration_checks.process``), the composed graph's both. A kernel builder below the
    fusion node is named nothing it does not earn."""
    if not name.endswith(CHILDREN):
        return ''
    return CHILD_ROLES.get(name.removesuffix(CHILDREN), '')


def descendants(pid: int | str = 'self') -> list[int]:
    """Every process below ``pid`` (Linux ``/proc/PID/task/*/children``): the adaptation's
    training process and a kernel builder belong to the graph's memory and CPU too."""
    found: list[int] = []
    stack = [pid]
    while stack:
        for task in Path(f'/proc/{stack.pop()}/task').glob('*'):
            try:
                kids = [int(k) for k in (task / 'children').read_text().split()]
            except (OSError, ValueError):
                continue
            found += kids
            stack += kids
    return found


class ProcessTree:
    """:func:`descendants` of each process asked for, walked again every ``refresh`` seconds
    (:data:`TREE_REFRESH_S`) and the same list returned in between: a graph run's CPU sampler
    (:class:`CpuSampler`) and the bench's memory sampler read its processes every progress call,
    from one cache."""

    def __init__(
        self, walk: Callable[[int | str], list[int]] = descendants, refresh: float = TREE_REFRESH_S
    ) -> None:
        self._walk, self.refresh = walk, refresh
        self._kids: dict[int | str, list[int]] = {}  # each process's descendants at the last walk
        self._walked: float | None = None

    def __call__(self, pid: int | str) -> list[int]:
        now = time.monotonic()
        if self._walked is None or now - self._walked >= self.refresh:
            self._kids, self._walked = {}, now
        kids = self._kids.get(pid)
        if kids is None:
            kids = self._kids[pid] = self._walk(pid)
        return kids


def cpu_seconds(pid: int | str = 'self') -> float:
    """User + system CPU seconds a live process has used (NaN when it cannot be read)."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except OSError:
        return float('nan')
    # The command name (2nd field) is in parentheses and may hold spaces: count after the last ')'.
    fields = stat.rsplit(')', 1)[-1].split()
    try:
        return (int(fields[11]) + int(fields[12])) / TICKS
    except (IndexError, ValueError):
        return float('nan')


def children_cpu_seconds(pids: Iterable[int]) -> float:
    """The live descendants' CPU seconds together (0 with none; one gone meanwhile counts 0)."""
    return sum(t for t in map(cpu_seconds, pids) if math.isfinite(t))


class CpuSampler:
    """Cumulative CPU seconds per graph process at each progress call, for :meth:`window`.

    ``processes``: the nodes run as processes (each one is read, the runner apart) or composed
    in this one (the runner is the graph). ``children(pid)`` lists a process's children and
    theirs (default :func:`descendants`; a test passes its own)."""

    def __init__(self, processes: bool, children: Callable[[int | str], list[int]] | None = None) -> None:
        self.processes = processes
        #: The processes' descendants, walked every :data:`TREE_REFRESH_S`; the bench's memory
        #: sampler reads the same cache (``bench.node_graph.MemorySampler``).
        self.tree = ProcessTree(children or descendants)
        self.samples: list[tuple[float, dict[str, float]]] = []

    def __call__(self, run) -> None:
        now = time.monotonic()
        values: dict[str, float] = {}
        if self.processes:
            values['runner'] = cpu_seconds()
            for name, proc in run.processes.items():
                self._read(values, name.removesuffix('_node'), proc.pid)
        else:
            self._read(values, 'graph', 'self')
        self.samples.append((now, values))

    def _read(self, values: dict[str, float], name: str, pid: int | str) -> None:
        values[name] = cpu_seconds(pid)
        kids = self.tree(pid)
        if kids:
            values[f'{name}{CHILDREN}'] = children_cpu_seconds(kids)

    def window(self, start: float, end: float) -> dict[str, float]:
        """CPU seconds each process used from ``start`` to ``end`` (monotonic s), read linearly
        between the samples around each end; only processes read at both ends and in between."""
        names = {n for _, values in self.samples for n in values}
        out = {}
        for name in sorted(names):
            series = [(t, v[name]) for t, v in self.samples if math.isfinite(v.get(name, math.nan))]
            first, last = _at(series, start), _at(series, end)
            if first is not None and last is not None:
                out[name] = max(0.0, last - first)
        return out


def _at(series: list[tuple[float, float]], t: float) -> float | None:
    """The cumulative value at ``t``, linear between the samples around it; None outside them."""
    for (t0, v0), (t1, v1) in itertools.pairwise(series):
        if t0 <= t <= t1:
            return v0 if t1 == t0 else v0 + (v1 - v0) * (t - t0) / (t1 - t0)
    return None


def budget_line(cpu: CpuSampler, fused: int, cores: int | None = None) -> str | None:
    """``CPU a fused keyframe: fusion 81 ms, multi_view 75 ms, ...; 1.93 of 2 cores`` over the
    samples' whole span (the playback), or None without figures (not Linux, no keyframe fused,
    fewer than two samples)."""
    if fused <= 0 or len(cpu.samples) < 2:
        return None
    start, end = cpu.samples[0][0], cpu.samples[-1][0]
    used = cpu.window(start, end)
    if not used or end <= start:
        return None
    parts = [
        f'{name}{f" ({role})" if (role := child_role(name)) else ""} {1e3 * seconds / fused:.0f} ms'
        for name, seconds in sorted(used.items(), key=lambda item: -item[1])
    ]
    cores = cores or os.cpu_count() or 1
    return (
        f'CPU a fused keyframe over the {end - start:.0f} s of playback: {", ".join(parts)}; '
        f'{sum(used.values()) / (end - start):.2f} of {cores} cores'
    )
