"""Node graph throughput, latency, drops and memory (``depth-fusion bench --only node_graph``).

Replays the first 100 frames of a sequence (``--sequence DIR``, converted once to a rosbag2
under ``artifacts/bench/``; a synthetic room when none is given; ``DEPTH_FUSION_BENCH_GRAPH_FRAMES``
plays more, so that the start of a stream weighs less in the flat-out rate) at the recorded 30 Hz
through the whole graph with the nodes' default parameters, in several runs (mode, pacing,
rate; ``DEPTH_FUSION_BENCH_GRAPH_RUNS``, default ``processes:paced:1,processes:realtime:1,
composed:paced:1,composed:realtime:1,processes:paced:10``: the last one plays 10x faster than
recorded, paced, so the graph runs flat out: its throughput is the highest sustainable
keyframe rate). ``DEPTH_FUSION_BENCH_GRAPH_SET`` overrides node parameters for every run, as
``run --set`` does (comma-separated ``NODE.PARAM=VALUE``, checked the same way), e.g.
``multi_view_node.keyframe_every=1`` for issue 13's "every frame a keyframe" on a GPU. Per run
it reports:

* time-to-ready of each node (start -> its "ready" line);
* keyframes the policy chose, fused, and dropped by node and reason (the run's summary);
* fused keyframes per second of the run (first image sent -> last keyframe fused), of its
  second half (the keyframes fused after the middle one: the rate once the start of the stream,
  the kernels' compile and the calibration checks' first samples, is behind), and of playback at
  the recorded rate (fused / recorded seconds);
* CPU milliseconds per fused keyframe of each process over that second half, and the cores
  they used together (``cpu_budget.py``, Linux): what holds the rate where it is;
* end-to-end latency per keyframe: input image arrival -> fused depth arrival, both seen by the
  runner's recorder (so it includes DDS transport both ways);
* peak resident memory (this process when composed; the sum of the node processes' peaks
  when separate; either with their child processes, such as the adaptation's training process).

With ``DEPTH_FUSION_BENCH_SOAK_SECONDS=600`` (or ``BenchOptions.soak_seconds``) it then loops the
bag for that long, composed, sampling the resident memory every few seconds, and reports it
at the start, middle and end of the soak and its trend: a flat line means bounded queues and
buffers really are bounded.
"""

from __future__ import annotations

import functools
import logging
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..cpu_budget import CpuSampler, child_role, descendants
from . import BenchOptions, BenchRow, load_note

TITLE = 'node graph (replayer -> multi-view + single-view -> fusion, real DDS)'

log = logging.getLogger(__name__)

BENCH_DIR = Path('artifacts') / 'bench'
SOAK_ENV = 'DEPTH_FUSION_BENCH_SOAK_SECONDS'
#: Keyframes in flight of a flat-out run (paced, faster than recorded): its figure is the
#: highest sustainable rate, which two pipelined keyframes raise (a replay's default is one).
FLAT_OUT_KEYFRAMES_IN_FLIGHT = 2
MODES_ENV = 'DEPTH_FUSION_BENCH_GRAPH_MODES'
RUNS_ENV = 'DEPTH_FUSION_BENCH_GRAPH_RUNS'
DEFAULT_RUNS = (
    'processes:paced:1,processes:realtime:1,composed:paced:1,composed:realtime:1,processes:paced:10'
)
MODEL_ENV = 'DEPTH_FUSION_BENCH_MODEL'
SET_ENV = 'DEPTH_FUSION_BENCH_GRAPH_SET'
FRAMES_ENV = 'DEPTH_FUSION_BENCH_GRAPH_FRAMES'
#: Frames of the bag a run plays, unless ``DEPTH_FUSION_BENCH_GRAPH_FRAMES`` says otherwise.
FRAMES = 100


def bench_frames(quick: bool) -> int:
    """Frames of the bag: 30 for ``--quick``, else ``DEPTH_FUSION_BENCH_GRAPH_FRAMES`` (a
    positive integer; anything else is an error, not a silent 100) or 100."""
    if quick:
        return 30
    raw = os.environ.get(FRAMES_ENV, '').strip()
    if not raw:
        return FRAMES
    try:
        frames = int(raw)
    except ValueError:
        frames = 0
    if frames < 2:
        raise ValueError(f'{FRAMES_ENV}: need an integer of at least 2 frames, got {raw!r}')
    return frames


#: What a node's warm line waits for (it processes inputs from its ready line on).
WARM_NOTES = {
    'fusion_node': 'ready before, at eager speed until the compiled kernels are in',
    'single_view_node': 'ready before (inference); warm once the training process is built',
}


def rss_mb(pid: int | str = 'self', field: str = 'VmRSS') -> float:
    """``VmRSS`` (current) or ``VmHWM`` (peak) of a process in MB, NaN when unknown."""
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith(field + ':'):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return float('nan')


def bench_bag(opts: BenchOptions) -> tuple[Path, str]:
    """A rosbag2 of the first frames of the benchmark sequence (converted once, cached)."""
    from ..data.rosbag_convert import tum_to_rosbag

    frames = bench_frames(opts.quick)
    BENCH_DIR.mkdir(parents=True, exist_ok=True)
    if opts.sequences:
        src = Path(opts.sequences[0])
        name = f'{src.name}_{frames}'
    else:
        from ..data.synthetic import SynthConfig, write_synthetic_sequence

        name = f'synthetic_{frames}'
        src = BENCH_DIR / name
        if not (src / 'rgb.txt').is_file():
            size = (320, 240) if opts.quick else (640, 480)
            write_synthetic_sequence(src, SynthConfig(width=size[0], height=size[1], frames=frames, seed=0))
    bag = BENCH_DIR / f'{name}_rosbag2'  # no .bag suffix: tools take *.bag for ROS 1
    if not (bag / 'metadata.yaml').is_file():
        tum_to_rosbag(src, bag, max_frames=frames, overwrite=True, show_progress=False)
    return bag, name


def env_overrides() -> dict[str, dict[str, object]]:
    """Node parameters from ``DEPTH_FUSION_BENCH_GRAPH_SET`` (checked like ``run --set``: a typo
    is an error, not a silently ignored override)."""
    return _parsed_overrides(os.environ.get(SET_ENV, ''))


@functools.lru_cache(maxsize=4)
def _parsed_overrides(spec: str) -> dict[str, dict[str, object]]:
    """Parsed and checked once per value (the check reads every node's parameter table)."""
    from ..cli.overrides import check_node_overrides, parse_overrides

    items = [i.strip() for i in spec.split(',') if i.strip()]
    try:
        overrides = parse_overrides(items, 'NODE')
        check_node_overrides(overrides)
    except ValueError as exc:
        raise ValueError(f'{SET_ENV}: {exc}') from None
    return overrides


def keyframe_every() -> int:
    """The multi-view node's keyframe spacing: ``DEPTH_FUSION_BENCH_GRAPH_SET``'s, else the
    default read from its parameter table's YAML (importing the node would load torch into the
    runner and inflate its memory figure)."""
    import yaml

    from ..nodes.config_yaml import find_config_file

    every = env_overrides().get('multi_view_node', {}).get('keyframe_every')
    if every is not None:
        return int(every)
    try:
        doc = yaml.safe_load(find_config_file().read_text())
        return int(doc['multi_view_node']['ros__parameters']['keyframe_every'])
    except (FileNotFoundError, KeyError, TypeError):
        from ..nodes.multi_view_params import PARAMETERS

        return int(next(p.default for p in PARAMETERS if p.name == 'keyframe_every'))


def image_count(bag: Path) -> int:
    from ..data.bag_open import open_bag
    from ..nodes.graph import TOPIC_IMAGE

    reader = open_bag(bag)
    try:
        return sum(c.msgcount for c in reader.connections if c.topic == TOPIC_IMAGE)
    finally:
        reader.close()


def tree_mb(
    pid: int | str = 'self', field: str = 'VmRSS', children: Callable[[int | str], list[int]] = descendants
) -> float:
    """:func:`rss_mb` of ``pid`` plus its descendants' (those gone meanwhile count 0); ``children``
    lists them (a run's ``cpu.tree``, :class:`~..cpu_budget.ProcessTree`, for a sampler that
    asks every tick)."""
    return rss_mb(pid, field) + sum(np.nan_to_num(rss_mb(d, field)) for d in children(pid))


class MemorySampler:
    """Resident memory of the graph (this process, or the node processes) over time."""

    def __init__(self, processes: bool) -> None:
        self.processes = processes
        self.samples: list[tuple[float, float]] = []
        self.peak_children: dict[str, float] = {}
        self.runner_max = 0.0
        self.t0 = time.monotonic()
        self.server: int | None = None

    def __call__(self, run) -> None:
        # Separate, the node processes are the runner's (or the fork server's) descendants:
        # each is counted once, with its own children. Their trees come from the run's CPU
        # sampler, which walks them every few seconds (cpu_budget.ProcessTree).
        tree = run.cpu.tree
        runner = rss_mb() if self.processes else tree_mb(children=tree)
        self.runner_max = max(self.runner_max, runner)
        if self.processes:
            total = 0.0
            from ..nodes.graph.forked import server_pid

            pids = {name: proc.pid for name, proc in run.processes.items()}
            if self.server is None:
                self.server = server_pid()  # the nodes are forked from it (graph/forked.py)
            if self.server is not None:
                pids['fork server'] = self.server
            for name, pid in pids.items():
                size = rss_mb if name == 'fork server' else functools.partial(tree_mb, children=tree)
                total += size(pid)
                self.peak_children[name] = max(self.peak_children.get(name, 0.0), size(pid, 'VmHWM'))
            self.samples.append((time.monotonic() - self.t0, total + runner))
        else:
            self.samples.append((time.monotonic() - self.t0, runner))

    def peak(self) -> float:
        """Peak of the graph: the node processes' own peaks plus the runner's largest sample, or,
        composed, the largest sample of this process (its high-water mark would include
        whatever ran before in the same process)."""
        if self.processes:
            return sum(self.peak_children.values()) + self.runner_max
        return self.runner_max


def graph_options(opts: BenchOptions, bag: Path, processes: bool, **extra):
    from ..nodes.graph import RunOptions

    overrides = {
        name: {'stats_period': 0.0} for name in ('single_view_node', 'multi_view_node', 'fusion_node')
    }
    for node, values in env_overrides().items():
        overrides.setdefault(node, {}).update(values)
    return RunOptions(
        bag=bag,
        processes=processes,
        device=opts.device,
        single_view_model=os.environ.get(MODEL_ENV) or None,
        overrides=overrides,
        track_input=True,
        flush_timeout=120.0,
        log_dir=BENCH_DIR / 'logs' if processes else None,
        **extra,
    )


def measure_run(
    opts: BenchOptions, bag: Path, processes: bool, realtime: bool = False, rate: float = 1.0
) -> list[BenchRow]:
    from ..nodes.graph import TOPIC_FUSED_DEPTH, TOPIC_IMAGE, GraphRun
    from ..nodes.graph.summary import drop_reasons, keyframe_summary

    mode = ('processes' if processes else 'composed') + (' real time' if realtime else ' paced')
    mode += f' x{rate:g}' if rate != 1.0 else ''
    sampler = MemorySampler(processes)
    options = graph_options(opts, bag, processes, on_progress=sampler, progress_period=0.5)
    options.realtime = realtime
    options.rate = rate
    if (
        rate > 1.0
        and not realtime
        and 'max_keyframes_in_flight' not in env_overrides().get('bag_replayer', {})
    ):
        options.max_keyframes_in_flight = FLAT_OUT_KEYFRAMES_IN_FLIGHT
    graph = GraphRun(options)
    result = graph.run()
    result.exit_codes = dict(graph.exit_codes)  # which processes ran: only their logs count
    spans = {'run': run_span(graph.recorder.stamp_logs, TOPIC_IMAGE, TOPIC_FUSED_DEPTH)}
    later_rate = second_half_rate(graph.recorder.stamp_logs, TOPIC_FUSED_DEPTH)
    images = image_count(bag)
    every = keyframe_every()
    expected = len([i for i in range(images) if i % every == 0 and i > 0])
    play_seconds = images / 30.0
    latencies = np.array(sorted(result.latencies.values())) * 1e3
    reasons = drop_reasons(result)
    log_drops = _drop_note(result, BENCH_DIR / 'logs' if processes else None)
    how = ''
    if processes:  # how the processes started, and so from when their time counts
        how = 'forked, counted from the fork server start' if graph.forked else 'console script'

    def ready_note(node: str) -> str:
        seconds = result.constructor_seconds.get(node)
        return '; '.join(p for p in (how, f'constructor {seconds:.1f} s' if seconds is not None else '') if p)

    rows = [
        BenchRow(f'{mode}: time to ready, {n.removesuffix("_node")}', t, 's', ready_note(n))
        for n, t in result.ready_seconds.items()
    ]
    rows += [
        BenchRow(
            f'{mode}: time to warm, {n.removesuffix("_node")}',
            t,
            's',
            f'{WARM_NOTES.get(n, "ready before")}; the replayer waits for this (bag_replayer.wait_warm)',
        )
        for n, t in result.warm_seconds.items()
    ]
    rows += [
        BenchRow(
            f'{mode}: keyframes chosen', len(result.chosen), 'kf', f'{expected} expected of {images} frames'
        ),
        BenchRow(
            f'{mode}: keyframes fused',
            len(result.fused),
            'kf',
            f'{100.0 * len(result.fused) / max(len(result.chosen), 1):.0f} % of chosen; {load_note()}',
        ),
        BenchRow(
            f'{mode}: keyframes dropped',
            sum(reasons.values()),
            'kf',
            ', '.join(f'{k}={v}' for k, v in sorted(reasons.items())) or log_drops,
        ),
    ]
    if realtime:  # a paced replay stretches the recording: only the run's own rate says anything
        rows.append(
            BenchRow(
                f'{mode}: fused kf per second of recording',
                len(result.fused) / play_seconds * rate,
                'kf/s',
                f'{images} frames at {30 * rate:g} Hz',
            )
        )
    if spans.get('run'):
        rows.append(
            BenchRow(
                f'{mode}: fused kf per second of the run',
                len(result.fused) / spans['run'],
                'kf/s',
                f'first image sent -> last keyframe fused: {spans["run"]:.1f} s',
            )
        )
    if later_rate is not None:
        rows.append(
            BenchRow(
                f'{mode}: fused kf per second of the second half',
                later_rate[0],
                'kf/s',
                f'{later_rate[1]} keyframes fused after the middle one, over {later_rate[2]:.1f} s',
            )
        )
    rows += cpu_rows(mode, graph.cpu, second_half(arrivals(graph.recorder.stamp_logs, TOPIC_FUSED_DEPTH)))
    if latencies.size:
        # In stamp order: the first seconds hold the fusion kernel's background compile (~6 s of
        # one core with torch's disk cache) and the adaptation's start; the second half is the
        # graph as it runs on. Both medians are printed, neither replaces the other.
        in_order = np.array([v for _, v in sorted(result.latencies.items())]) * 1e3
        later = in_order[in_order.size // 2 :]
        rows += [
            BenchRow(f'{mode}: latency image -> fused, median', float(np.median(latencies)), 'ms'),
            BenchRow(
                f'{mode}: latency image -> fused, median of the second half',
                float(np.median(later)),
                'ms',
                f'the last {later.size} of {in_order.size} keyframes (after warm-up)',
            ),
            BenchRow(f'{mode}: latency image -> fused, p95', float(np.percentile(latencies, 95)), 'ms'),
            BenchRow(f'{mode}: latency image -> fused, max', float(latencies.max()), 'ms'),
        ]
    for node, ms in node_latencies(result, BENCH_DIR / 'logs' if processes else None).items():
        rows.append(
            BenchRow(f'{mode}: {node} latency in -> out, mean', ms, 'ms', 'per keyframe, queue wait included')
        )
    rows.append(BenchRow(f'{mode}: peak resident memory', sampler.peak(), 'MB', _peak_note(sampler)))
    rows.append(
        BenchRow(
            f'{mode}: wall time incl. start-up and flush', result.seconds, 's', keyframe_summary(result, mode)
        )
    )
    return rows


def run_span(logs: dict, first: str, last: str) -> float:
    """Seconds from the first message of ``first`` to the last of ``last`` seen by the recorder."""
    starts, ends = arrivals(logs, first), arrivals(logs, last)
    return max(ends) - min(starts) if starts and ends else 0.0


def arrivals(logs: dict, topic: str) -> list[float]:
    """Arrival times (monotonic s) of the messages the recorder saw on ``topic``, sorted."""
    if topic not in logs:
        return []
    return sorted(t for t in map(logs[topic].arrival, logs[topic].stamps()) if t is not None)


def second_half(times: list[float]) -> tuple[float, float, int] | None:
    """The second half of a run from sorted arrival times: from the middle arrival to the last,
    and how many arrived after the middle one; None with fewer than 5 or no time between. The
    window of both the second half's rate and its CPU budget."""
    if len(times) < 5:
        return None
    middle = len(times) // 2
    start, end = times[middle], times[-1]
    return (start, end, len(times) - 1 - middle) if end > start else None


def second_half_rate(logs: dict, topic: str) -> tuple[float, int, float] | None:
    """Keyframes per second after the middle arrival on ``topic`` (the rate, how many, over how many
    seconds), or None with fewer than 5 arrivals: the rate the graph keeps once the start of a
    stream is behind it, which the run's own rate mixes with that start."""
    window = second_half(arrivals(logs, topic))
    if window is None:
        return None
    start, end, count = window
    return count / (end - start), count, end - start


def cpu_rows(mode: str, cpu: CpuSampler, window: tuple[float, float, int] | None) -> list[BenchRow]:
    """CPU milliseconds per fused keyframe of each process over the second half's ``window``
    (:func:`second_half`, as "fused kf per second of the second half"), and the cores they used
    together; none without a window or where ``/proc`` gave nothing (not Linux)."""
    if window is None:
        return []
    start, end, count = window
    used = cpu.window(start, end)
    if not used:
        return []
    cores = os.cpu_count() or 1
    rows = [
        BenchRow(
            f'{mode}: CPU per fused keyframe, {name}',
            1e3 * seconds / count,
            'ms',
            f'second half, {seconds / (end - start):.2f} cores' + _child_note(name),
        )
        for name, seconds in sorted(used.items(), key=lambda item: -item[1])
    ]
    total = sum(used.values())
    rows.append(
        BenchRow(
            f'{mode}: CPU of the second half, all processes',
            total / (end - start),
            'cores',
            f'of {cores}; {1e3 * total / count:.0f} ms per fused keyframe over {count} keyframes',
        )
    )
    return rows


def _child_note(name: str) -> str:
    """What a row's child processes are (``cpu_budget.child_role``)."""
    role = child_role(name)
    return f'; {role}' if role else ''


def node_latencies(result, log_dir: Path | None) -> dict[str, float]:
    """Per node, mean ms from an input's arrival to its output (the profile: which node is
    the bottleneck), from the composed nodes' counters or the processes' final log lines."""
    out = {
        name.removesuffix('_node'): snap.latency_mean_s * 1e3
        for name, snap in result.node_stats.items()
        if snap.processed
    }
    if log_dir is not None:
        for log_file in run_logs(log_dir, result):
            if not log_file.stem.endswith('_node'):
                continue
            finals = [
                ln for ln in log_file.read_text(errors='replace').splitlines() if 'final counters:' in ln
            ]
            match = re.search(r'latency mean ([0-9.]+) ms', finals[-1]) if finals else None
            if match:
                out[log_file.stem.removesuffix('_node')] = float(match.group(1))
    return out


def run_logs(log_dir: Path, result) -> list[Path]:
    """The log files of this run's processes (an earlier run in the same folder may have
    started other nodes, e.g. map_node in a soak: their old logs are not this run's)."""
    ran = set(getattr(result, 'exit_codes', None) or {})
    return [f for f in sorted(log_dir.glob('*.log')) if not ran or f.stem in ran]


def logged_drops(log_dir: Path, result=None) -> dict[str, dict[str, int]]:
    """Drop counters of node processes, from the ``final counters: ... dropped N (a=1 b=2)`` lines."""
    out: dict[str, dict[str, int]] = {}
    for log_file in run_logs(log_dir, result):
        finals = [ln for ln in log_file.read_text(errors='replace').splitlines() if 'final counters:' in ln]
        match = re.search(r'dropped \d+ \(([^)]*)\)', finals[-1]) if finals else None
        if match:
            pairs = (item.split('=') for item in match.group(1).split())
            out[log_file.stem] = {k: int(v) for k, v in pairs}
    return out


def _drop_note(result, log_dir: Path | None = None) -> str:
    counters = {name: snap.dropped for name, snap in result.node_stats.items()}
    if log_dir is not None:
        counters.update(logged_drops(log_dir, result))
    drops = {}
    for name, dropped in counters.items():
        for reason, count in dropped.items():
            drops[f'{name.removesuffix("_node")}.{reason}'] = count
    missing = f'{len(result.missing)} announced but not fused' if result.missing else ''
    parts = [', '.join(f'{k}={v}' for k, v in sorted(drops.items())), missing]
    return '; '.join(p for p in parts if p)


def _peak_note(sampler: MemorySampler) -> str:
    if sampler.processes:
        parts = [f'{k.removesuffix("_node")} {v:.0f}' for k, v in sampler.peak_children.items()]
        return ' + '.join([*parts, f'runner {sampler.runner_max:.0f}'])
    return 'whole process (torch, rclpy, all nodes) with its child processes, sampled every 0.5 s'


def soak(opts: BenchOptions, bag: Path, seconds: float) -> list[BenchRow]:
    """Loop the bag for ``seconds`` (composed) and report the resident memory over time."""
    from ..nodes.graph import run_graph

    sampler = MemorySampler(processes=False)
    period = max(1.0, seconds / 120)
    overrides = {'bag_replayer': {'loop': True, 'loop_seconds': float(seconds)}}
    options = graph_options(opts, bag, False, on_progress=sampler, progress_period=period)
    options.track_input = False
    for node, values in overrides.items():
        options.overrides.setdefault(node, {}).update(values)
    result = run_graph(options)
    samples = np.array(sampler.samples)
    curve = BENCH_DIR / 'soak_rss.csv'
    np.savetxt(curve, samples, fmt='%.1f', delimiter=',', header='seconds,rss_mb', comments='')
    if len(samples) < 3:
        return [BenchRow('soak: too short to sample', seconds, 's')]
    t, rss = samples[:, 0], samples[:, 1]
    # Warm-up (allocator pools, torch caches) is over after the first tenth of the run.
    steady = t >= t[-1] * 0.1
    slope = float(np.polyfit(t[steady], rss[steady], 1)[0]) * 60.0 if steady.sum() >= 2 else float('nan')
    mid = len(rss) // 2
    return [
        BenchRow(
            'soak: looped replay',
            seconds,
            's',
            f'{len(result.fused)} keyframes fused; {load_note()}; curve in {curve}',
        ),
        BenchRow('soak: resident memory at start', float(rss[0]), 'MB', f't={t[0]:.0f} s'),
        BenchRow(
            'soak: resident memory after warm-up', float(rss[steady][0]), 'MB', f't={t[steady][0]:.0f} s'
        ),
        BenchRow('soak: resident memory at middle', float(rss[mid]), 'MB', f't={t[mid]:.0f} s'),
        BenchRow('soak: resident memory at end', float(rss[-1]), 'MB', f't={t[-1]:.0f} s'),
        BenchRow('soak: resident memory trend after warm-up', slope, 'MB/min'),
        BenchRow('soak: peak resident memory', sampler.peak(), 'MB'),
    ]


def graph_runs(opts: BenchOptions) -> list[tuple[str, str, float]]:
    """``[(mode, pacing, rate), ...]`` from ``DEPTH_FUSION_BENCH_GRAPH_RUNS`` (or the older
    ``DEPTH_FUSION_BENCH_GRAPH_MODES``: those modes, paced, at the recorded rate)."""
    if os.environ.get(MODES_ENV) and not os.environ.get(RUNS_ENV):
        spec = ','.join(f'{m.strip()}:paced:1' for m in os.environ[MODES_ENV].split(',') if m.strip())
    else:
        spec = os.environ.get(RUNS_ENV) or ('composed:paced:1' if opts.quick else DEFAULT_RUNS)
    runs = []
    for item in (i.strip() for i in spec.split(',') if i.strip()):
        parts = item.split(':')
        mode, pacing = parts[0], parts[1] if len(parts) > 1 else 'paced'
        try:
            rate = float(parts[2]) if len(parts) > 2 else 1.0
        except ValueError:
            rate = -1.0
        if mode not in ('composed', 'processes') or pacing not in ('paced', 'realtime') or rate <= 0:
            raise ValueError(f'{RUNS_ENV}: bad run {item!r} (MODE:PACING:RATE, e.g. processes:realtime:1)')
        runs.append((mode, pacing, rate))
    return runs


def run(opts: BenchOptions) -> list[BenchRow]:
    bag, name = bench_bag(opts)
    # Processes first: the runner then holds no torch and no composed nodes, so its own memory
    # (counted in the processes' peak) is the runner's alone.
    rows = [BenchRow(f'bag: {name}', image_count(bag), 'frames', str(bag))]
    if os.environ.get(SET_ENV):
        rows.append(BenchRow(f'node parameters: {os.environ[SET_ENV]}', float('nan'), '', SET_ENV))
    for mode, pacing, rate in graph_runs(opts):
        rows += measure_run(opts, bag, mode == 'processes', pacing == 'realtime', rate)
    seconds = float(getattr(opts, 'soak_seconds', 0.0) or os.environ.get(SOAK_ENV, 0) or 0)
    if seconds > 0:
        rows += soak(opts, bag, seconds)
    return rows
