"""Soak: does the graph's memory stay flat over a long looped replay? (``--only soak``)

Not part of the normal sections (it runs for ``DEPTH_FUSION_SOAK_SECONDS``, default 1800 s =
30 min): ``scripts/soak.sh`` or ``depth-fusion bench --only soak``. The benchmark bag is
looped (header stamps shifted each pass, so the nodes see time moving forward) through the
graph **as processes**, the way a robot runs it, with the nodes' default (live) queues. Every
few seconds the resident memory (VmRSS) of the runner and of each node process is sampled.

Reported (figures, never assertions):

* the graph's total RSS after warm-up (the first 20 % of the run, at least 30 s: allocator
  pools, torch caches and DDS histories fill up) and at the end (median of the last 5 % of
  samples, so one GC pause does not decide it);
* the growth from warm-up to end, and the largest excursion above the warm-up level, in %
  (the target: within 5 %), and the trend in MB/min;
* the same growth per process, so a leak is attributed to a node.

The curve goes to ``artifacts/bench/soak_rss.csv`` (seconds, total, then one column per process).

With ``DEPTH_FUSION_SOAK_MAP_BLOCKS=N`` the graph also runs ``map_node`` (``--map``) with
``map.max_blocks = N``: set N below what the scene needs and the map evicts blocks all along,
so the run shows whether the map node's memory stays under its declared cap over the whole
looped replay: N x ``MapConfig.bytes_per_block`` for the voxels, plus the keyframes it keeps
for a rebuild at corrected poses (``reintegration_max_mb``).
"""

from __future__ import annotations

import os
import time

import numpy as np

from . import BenchOptions, BenchRow, load_note
from .node_graph import BENCH_DIR, bench_bag, graph_options, rss_mb

TITLE = 'soak (looped replay as processes, resident memory over time)'
SECONDS_ENV = 'DEPTH_FUSION_SOAK_SECONDS'
MAP_BLOCKS_ENV = 'DEPTH_FUSION_SOAK_MAP_BLOCKS'
DEFAULT_SECONDS = 1800.0
#: Share of the run counted as warm-up.
WARMUP_SHARE = 0.2
TARGET_PERCENT = 5.0


class ProcessSampler:
    """RSS of the runner and of each node process, over time (an ``on_progress`` callback)."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self.times: list[float] = []
        self.rss: list[dict[str, float]] = []

    def __call__(self, run) -> None:
        sample = {'runner': rss_mb()}
        for name, proc in run.processes.items():
            sample[name] = rss_mb(proc.pid)
        self.times.append(time.monotonic() - self.t0)
        self.rss.append(sample)


def steady_window(t: np.ndarray, total_seconds: float) -> np.ndarray:
    """Samples after warm-up: past ``WARMUP_SHARE`` of the run (at least 30 s), and at most
    the first half of what was sampled."""
    return t >= min(max(30.0, WARMUP_SHARE * total_seconds), t[-1] * 0.5)


def growth(t: np.ndarray, values: np.ndarray, total_seconds: float) -> tuple[float, float, float, float]:
    """(warm-up level, end level, growth %, max excursion %) of one RSS series."""
    steady = steady_window(t, total_seconds)
    s_v = values[steady]
    head = s_v[: max(1, len(s_v) // 20)]
    tail = s_v[-max(1, len(s_v) // 20) :]
    warm, end = float(np.median(head)), float(np.median(tail))
    return warm, end, 100.0 * (end / warm - 1.0), 100.0 * (float(s_v.max()) / warm - 1.0)


def run(opts: BenchOptions) -> list[BenchRow]:
    from ..nodes.graph import run_graph

    seconds = float(os.environ.get(SECONDS_ENV, DEFAULT_SECONDS))
    bag, name = bench_bag(opts)
    sampler = ProcessSampler()
    period = max(2.0, seconds / 300)
    options = graph_options(opts, bag, True, on_progress=sampler, progress_period=period)
    options.track_input = False
    options.overrides.setdefault('bag_replayer', {}).update({'loop': True, 'loop_seconds': seconds})
    options.flush_timeout = 30.0
    map_blocks = int(os.environ.get(MAP_BLOCKS_ENV, '0') or 0)
    if map_blocks > 0:
        options.map = True
        options.overrides.setdefault('map_node', {}).update({'map.max_blocks': map_blocks})
    result = run_graph(options)
    names = sorted({k for s in sampler.rss for k in s})
    if len(sampler.times) < 6:
        return [BenchRow('soak: too short to sample', seconds, 's')]
    t = np.asarray(sampler.times)
    table = np.array([[s.get(n, np.nan) for n in names] for s in sampler.rss])
    total = np.nansum(table, axis=1)
    curve = BENCH_DIR / 'soak_rss.csv'
    np.savetxt(
        curve, np.column_stack([t, total, table]), fmt='%.1f', delimiter=',',
        header='seconds,total_mb,' + ','.join(f'{n}_mb' for n in names), comments='',
    )  # fmt: skip
    warm, end, grew, peak = growth(t, total, seconds)
    steady = steady_window(t, seconds)
    slope = float(np.polyfit(t[steady], total[steady], 1)[0]) * 60.0
    verdict = 'within' if abs(grew) <= TARGET_PERCENT and peak <= TARGET_PERCENT else 'OUTSIDE'
    rows = [
        BenchRow(
            'soak: looped replay as processes',
            t[-1],
            's',
            f'{name}; {len(result.fused)} keyframes fused; {load_note()}; curve in {curve}',
        ),
        BenchRow('soak: graph RSS after warm-up', warm, 'MB', f'runner + {len(names) - 1} node processes'),
        BenchRow('soak: graph RSS at end', end, 'MB'),
        BenchRow('soak: growth warm-up -> end', grew, '%', f'{verdict} the {TARGET_PERCENT:g} % target'),
        BenchRow('soak: largest excursion above warm-up', peak, '%'),
        BenchRow('soak: trend after warm-up', slope, 'MB/min'),
    ]
    for i, n in enumerate(names):
        w, e, g, _ = growth(t, table[:, i], seconds)
        rows.append(BenchRow(f'soak: {n} RSS growth', g, '%', f'{w:.0f} -> {e:.0f} MB'))
    if map_blocks > 0 and 'map_node' in names:
        rows += map_rows(t, table[:, names.index('map_node')], seconds, map_blocks)
    return rows


def map_rows(
    t: np.ndarray, rss: np.ndarray, seconds: float, max_blocks: int, kept_mb: float = 128.0
) -> list[BenchRow]:
    """map_node's memory against its declared cap: how far its RSS rose above the level after
    warm-up (torch, rclpy and the first keyframes), at most, compared with the voxel cap plus
    the cap of the keyframes kept for a rebuild (``reintegration_max_mb``, the node's default)."""
    from ..mapping.config import MapConfig

    voxels = max_blocks * MapConfig().bytes_per_block / 2**20
    cap = voxels + kept_mb
    warm, end, _, _ = growth(t, rss, seconds)
    rise = float(np.nanmax(rss[steady_window(t, seconds)])) - warm
    verdict = 'under' if rise <= cap else 'OVER'
    return [
        BenchRow(
            'soak: map_node declared cap',
            cap,
            'MB',
            f'voxels {voxels:.0f} MB (map.max_blocks={max_blocks}) + kept keyframes {kept_mb:.0f} MB '
            f'(reintegration_max_mb={kept_mb:g})',
        ),
        BenchRow(
            'soak: map_node RSS largest rise after warm-up',
            rise,
            'MB',
            f'{verdict} the cap; {warm:.0f} MB after warm-up, {end:.0f} MB at the end',
        ),
    ]
