"""Multi-view benchmark rows of the temporal depth filter (``multi_view.method: filter``).

The issue's target: one filter update (one posed frame) costs at most 1/5 of today's sweep
of one keyframe (4 neighbours), on 2 CPU cores, so that the filter keeps up with every frame
while the sweep runs on keyframes only. Both are timed here back to back on the same frames
(the load of a shared machine moves both alike): the filter over the whole stream (mean and
median per frame, keyframe switches included), the sweep on the middle frame with its
offline neighbours, as the sweep rows of ``bench.multi_view``.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from ..data.sequence import Sequence
from ..multiview.filter import DepthFilter
from ..multiview.neighbours import select_neighbours
from ..multiview.semidense import MultiViewConfig, estimate_semidense, select_best_fraction
from . import BenchOptions, BenchRow


def _note(extra: str = '') -> str:
    import os

    base = f'load {os.getloadavg()[0]:.1f}, {torch.get_num_threads()} threads'
    return f'{extra}; {base}' if extra else base


def _stream_seconds(seq: Sequence, device: str) -> tuple[list[float], DepthFilter]:
    f = DepthFilter(seq.camera, device=device)
    seconds = []
    for frame in seq.frames:
        gray, pose = frame.gray, frame.pose
        t0 = time.perf_counter()
        f.process(gray, pose)
        if f.device.type == 'cuda':
            torch.cuda.synchronize(f.device)
        seconds.append(time.perf_counter() - t0)
    return seconds, f


def _sweep_seconds(seq: Sequence, key: int, device: str, repeats: int) -> float:
    chosen = select_neighbours(seq.poses, key, 4, 'offline', seq.camera)
    fr = seq.frames
    grays, poses = [fr[i].gray for i in chosen], [fr[i].pose for i in chosen]
    args = (fr[key].gray, fr[key].pose, grays, poses, seq.camera)
    estimate_semidense(*args, MultiViewConfig(), device=device)  # warm-up
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        estimate_semidense(*args, MultiViewConfig(), device=device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def filter_rows(label: str, seq: Sequence, opts: BenchOptions) -> list[BenchRow]:
    """Per-frame filter cost against the per-keyframe sweep, and the filter's accuracy."""
    _stream_seconds(seq, opts.device)  # warm-up (allocations, first descriptors)
    seconds, f = _stream_seconds(seq, opts.device)
    steady = seconds[1:]  # the first frame only makes the first keyframe
    sweep = _sweep_seconds(seq, len(seq) // 2, opts.device, opts.repeats)
    mean = statistics.fmean(steady)
    last = len(seq) - 1
    result = f.result(seq.frames[last].pose)
    gt = seq.gt_depth_working(last)
    rows = [
        BenchRow(f'{label}: filter per frame (mean)', mean * 1e3, 'ms', _note(f'{f.stats}')),
        BenchRow(f'{label}: filter per frame (median)', statistics.median(steady) * 1e3, 'ms', _note()),
        BenchRow(f'{label}: sweep per keyframe (same load)', sweep * 1e3, 'ms', _note()),
        BenchRow(
            f'{label}: filter per frame / sweep per keyframe', mean / sweep, 'ratio', _note('target <= 0.2')
        ),
    ]
    if gt is not None:
        valid = np.isfinite(result.depth) & np.isfinite(gt) & (gt > 0)
        rel = np.abs(result.depth - gt) / np.where(valid, gt, 1.0)
        selected = select_best_fraction(result, 0.25) & valid
        rows += [
            BenchRow(f'{label}: filter density', result.density, 'fraction', _note('last frame')),
            BenchRow(
                f'{label}: filter density with AbsRel <= 10 %',
                float((valid & (rel <= 0.1)).mean()),
                'fraction',
                _note('last frame'),
            ),
            BenchRow(
                f'{label}: filter selected median AbsRel',
                float(np.median(rel[selected])) if selected.any() else float('nan'),
                'ratio',
                _note(f'{selected.mean():.3%} of pixels selected'),
            ),
        ]
    return rows
