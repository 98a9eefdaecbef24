"""What a run is told (:class:`RunOptions`) and what it reports (:class:`RunResult`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .lifecycle import GraphRun


@dataclass
class RunOptions:
    """Everything ``depth-fusion run`` can be told (the CLI flags)."""

    bag: Path
    params_file: Path | None = None
    #: rosbag2 folder to write the outputs to (``None``: nothing written, outputs still tracked).
    record: Path | None = None
    record_storage: str = 'mcap'
    #: Extra topics to record besides :data:`RECORDED_TOPICS` (type from the graph).
    record_extra: list[str] = field(default_factory=list)
    processes: bool = False
    #: Play at the recorded rate whatever the graph does (drops reported); default: a paced,
    #: lossless replay that waits while the graph is busy (see :mod:`.pacing`).
    realtime: bool = False
    #: Paced replay: chosen keyframes unfinished at most (``None``: the replayer's default).
    max_keyframes_in_flight: int | None = None
    #: Replayer settings; ``None`` leaves the params file (or the default) in charge.
    rate: float | None = None
    start_offset: float | None = None
    #: Torch device of the three nodes and the single-view model (``None``: params file).
    device: str | None = None
    single_view_model: str | None = None
    #: ``{node name: {parameter: value}}`` applied on top of the params file.
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: Seconds to wait after the end of the bag for announced keyframes to be fused.
    flush_timeout: float = 60.0
    #: The outputs count as flushed once nothing new arrived for this long.
    settle: float = 1.0
    #: Processes: keyframes still in flight after this long without any output are given up.
    idle_timeout: float = 30.0
    #: Torch/OpenMP threads per node process (``None``: cores / 3 unless OMP_NUM_THREADS is
    #: set), so three processes do not oversubscribe the cores. Composed, the three nodes'
    #: workers share one torch pool: ``None`` means 1 thread (each worker then keeps a core
    #: busy on its own; measured 4x more keyframes fused than 2 shared threads on 2 cores).
    threads_per_node: int | None = None
    #: Processes: seconds for the nodes to start (torch import, model load) before giving up.
    startup_timeout: float = 120.0
    #: Seconds the replayer waits, once the nodes are ready, for those warming up in the
    #: background (fusion kernels compiling) to be warm; then it plays anyway (0: at once).
    warm_timeout: float = 60.0
    #: Threads of the runner's own executor (its recorder; composed nodes each spin on their
    #: own single-threaded executor, as they do in their own processes).
    executor_threads: int = 4
    #: Processes: folder for each child's log (``None``: children log to this terminal).
    log_dir: Path | None = None
    #: Log the input image stamps too (latency measurement by the benchmark).
    track_input: bool = False
    #: Called about every ``progress_period`` s while the bag plays (benchmark sampling).
    on_progress: Callable[[GraphRun], None] | None = None
    progress_period: float = 1.0
    #: ROS domain of the graph (``None``: a free private one, see :mod:`.isolation`).
    domain_id: int | None = None
    #: Localhost-only discovery (``None``: yes for a private domain, no with ``domain_id``).
    localhost_only: bool | None = None
    #: Run even when the bag lacks a topic the graph needs (``--allow-missing``).
    allow_missing: bool = False
    #: Also start ``map_node`` (``--map``), which integrates every fused keyframe into a TSDF.
    map: bool = False
    #: Write the map's mesh here when the run ends (``--save-map FILE.ply``; implies ``map``).
    save_map: Path | None = None

    @property
    def with_map(self) -> bool:
        return self.map or self.save_map is not None


@dataclass
class RunResult:
    """What happened: keyframes announced and fused, what was lost, where the bag is."""

    announced: list[int]
    fused: list[int]
    missing: dict[int, str]
    recorded: Path | None
    counts: dict[str, int]
    seconds: float
    interrupted: bool = False
    #: Per node, its final counters (composed mode only: the processes log theirs).
    node_stats: dict[str, Any] = field(default_factory=dict)
    #: Seconds from input image arrival to fused depth arrival, per keyframe (track_input).
    latencies: dict[int, float] = field(default_factory=dict)
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    #: Every keyframe the keyframe policy chose (announced or not), and those given up -> why
    #: (``'multi_view.worker_queue_full'`` ...), from the nodes' keyframe events.
    chosen: list[int] = field(default_factory=list)
    drops: dict[int, str] = field(default_factory=dict)
    paced: bool = True
    #: Per node, seconds from its start to its "ready" line (time-to-ready).
    ready_seconds: dict[str, float] = field(default_factory=dict)
    #: Camera images the replayer sent (``None``: unknown) and multi_view_node handled
    #: (posed, or dropped with a reason): the gap was lost on the way (DDS history overflow).
    images_played: int | None = None
    images_handled: int = 0
    #: Per node, of those the seconds its constructor took (the rest: interpreter, imports).
    constructor_seconds: dict[str, float] = field(default_factory=dict)
    #: Nodes that were ready before warm (kernels compiling in the background): seconds from
    #: their start to their warm line.
    warm_seconds: dict[str, float] = field(default_factory=dict)
    #: The ROS domain the graph ran on.
    domain_id: int | None = None
    #: ``--save-map``: the mesh file written, and its vertex and triangle counts; or why not.
    map_file: Path | None = None
    map_size: tuple[int, int] | None = None
    map_error: str | None = None
    #: Topics asked to be recorded that no publisher of the graph announced (never subscribed).
    unannounced: list[str] = field(default_factory=list)
    #: Where the cores went: CPU per fused keyframe of each process over the playback
    #: (``cpu_budget.budget_line``); None where ``/proc`` gave nothing.
    cpu_budget: str | None = None

    @property
    def complete(self) -> bool:
        return not self.missing and not self.interrupted


class GraphError(RuntimeError):
    """The graph could not run to the end (a node died, the replayer failed).

    ``result`` holds how far it got (keyframes fused, the partial recording) when the graph
    had started.
    """

    result: RunResult | None = None
