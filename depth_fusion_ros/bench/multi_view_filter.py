"""Multi-view benchmark rows of the temporal depth filter (``multi_view.method: filter``).

The issue's target: one filter update (one posed frame) costs at most 1/5 of today's sweep
of one keyframe (4 neighbours), on 2 CPU cores, so that the filter keeps up with every frame
while the sweep runs on keyframes only. Both are timed here back to back on the same frames
(the load of a shared machine moves both alike): the filter over the whole stream (mean and
median per frame, keyframe switches included), the sweep on the middle frame with its
offline neighbours, as the sweep rows of ``bench.multi_view``. The accuracy rows give the
issue's density target: pixels with an estimate within 10 % of the ground truth (of all
pixels), filter against sweep (target >= 2x), at an equal or better stage-1 median AbsRel.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from ..data.sequence import Sequence
from ..metrics import good_density
from ..multiview.filter import DepthFilter
from ..multiview.semidense import MultiViewConfig, estimate_semidense, select_best_fraction
from . import BenchOptions, BenchRow
from .multi_view import _keyframe_inputs, _median_abs_rel, _real_sequence, _synthetic_sequence

TITLE = 'multi_view_filter (temporal inverse-depth filter against the per-keyframe sweep)'


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
    args = _keyframe_inputs(seq, key)
    estimate_semidense(*args, MultiViewConfig(), device=device)  # warm-up
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        estimate_semidense(*args, MultiViewConfig(), device=device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _accuracy(depth: np.ndarray, gt: np.ndarray, selected: np.ndarray) -> tuple[float, float]:
    """Good density (AbsRel <= 10 %, of all pixels) and the selected points' median AbsRel."""
    return good_density(depth, gt), _median_abs_rel(depth, gt, selected & np.isfinite(depth))


def filter_rows(label: str, seq: Sequence, opts: BenchOptions) -> list[BenchRow]:
    """Per-frame filter cost against the per-keyframe sweep, and both methods' accuracy.

    Accuracy on the last frame, both causal: the filter after the whole stream, the sweep
    with its online neighbours (the past frames the node would have).
    """
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
        fraction = MultiViewConfig().select_fraction
        good, selected = _accuracy(result.depth, gt, select_best_fraction(result, fraction))
        swept = estimate_semidense(
            *_keyframe_inputs(seq, last, 'online'), MultiViewConfig(), device=opts.device
        )
        sweep_good, sweep_selected = _accuracy(swept.depth, gt, select_best_fraction(swept, fraction))
        rows += [
            BenchRow(f'{label}: filter density', result.density, 'fraction', _note('last frame')),
            BenchRow(f'{label}: filter density with AbsRel <= 10 %', good, 'fraction', _note('last frame')),
            BenchRow(
                f'{label}: sweep density with AbsRel <= 10 %',
                sweep_good,
                'fraction',
                _note('last frame, online neighbours'),
            ),
            BenchRow(
                f'{label}: filter / sweep density with AbsRel <= 10 %',
                good / sweep_good if sweep_good > 0 else float('nan'),
                'ratio',
                _note('target >= 2'),
            ),
            BenchRow(f'{label}: filter selected median AbsRel', selected, 'ratio', _note('stage 1')),
            BenchRow(
                f'{label}: sweep selected median AbsRel',
                sweep_selected,
                'ratio',
                _note('target: filter <= this'),
            ),
        ]
    return rows


def run(opts: BenchOptions) -> list[BenchRow]:
    """The synthetic room, then each ``--sequence`` (its first frames), as ``bench.multi_view``."""
    rows = filter_rows('synthetic room', _synthetic_sequence(opts.quick), opts)
    for path in opts.sequences:
        real = _real_sequence(path, opts.quick)
        rows += filter_rows(real.name, real, opts)
    return rows
