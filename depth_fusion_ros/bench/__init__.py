"""Benchmarks printed by ``depth-fusion bench`` (figures, never assertions).

One module per stage (``synthetic``, ``image_input``, ``multi_view``, ``multi_view_filter``,
``single_view``, ``adaptation``, ``fusion``, ``mapping``, ``node_graph``), each exposing::

    TITLE: str
    def run(opts: BenchOptions) -> list[BenchRow]

so ``depth-fusion bench --only fusion`` runs one section.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class BenchOptions:
    device: str = 'cpu'
    #: Fewer repetitions and smaller inputs: a smoke run, not a measurement.
    quick: bool = False
    repeats: int = 5
    #: Optional TUM folders (e.g. ../shared/data/...) for sections that measure on real data.
    sequences: list[str] = field(default_factory=list)
    #: node_graph: seconds of looped replay to watch memory over (0: no soak); the CLI has no
    #: flag for it, the environment variable DEPTH_FUSION_BENCH_SOAK_SECONDS sets it there.
    soak_seconds: float = 0.0


@dataclass
class BenchRow:
    name: str
    value: float
    unit: str
    note: str = ''


SECTIONS = (
    'synthetic',
    'image_input',
    'multi_view',
    'multi_view_filter',
    'single_view',
    'adaptation',
    'fusion',
    'mapping',
    'node_graph',
)


def load_note(extra: str = '') -> str:
    """``extra`` and the 1-minute load average: runs share the CPU, so figures need it beside them."""
    try:
        load = f'load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores'
    except OSError:
        load = ''
    return '; '.join(s for s in (extra, load) if s)


def median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones (caches,
    first-call allocations and compiled kernels are then out of the figure)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)
