"""Benchmarks printed by ``depth-fusion bench`` (figures, never assertions).

One module per stage (``synthetic``, ``image_input``, ``multi_view``, ``multi_view_filter``,
``single_view``, ``adaptation``, ``fusion``, ``mapping``, ``node_graph``), each exposing::

    TITLE: str
    def run(opts: BenchOptions) -> list[BenchRow]

so ``depth-fusion bench --only fusion`` runs one section.
"""

from __future__ import annotations

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
