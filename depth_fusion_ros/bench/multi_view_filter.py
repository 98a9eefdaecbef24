"""Multi-view benchmark rows of the temporal depth filter (``multi_view.method: filter``).

The issue's target: one filter update (one posed frame) costs at most 1/5 of today's sweep
of one keyframe (4 neighbours), on 2 CPU cores, so that the filter keeps up with every frame
while the sweep runs on keyframes only. Both are timed here interleaved on the same frames
(each pass of the filter, then one sweep: the load and the speed of a shared machine move both
alike): the filter over the whole stream (mean per frame, keyframe switches included), the
sweep on the middle frame with its offline neighbours, as the sweep rows of
``bench.multi_view``. Each cost is printed twice:
wall clock, and the CPU time of the process (``time.process_time``; with one torch thread the
CPU time of that thread), which a shared machine's load moves much less: the ratio of CPU
times is the figure to compare. The accuracy rows give the issue's density target: pixels
with an estimate within 10 % of the ground truth (of all pixels), filter against sweep
(target >= 2x), at an equal or better stage-1 median AbsRel. A keyframe stream (the
``keyframes`` stress case: every frame far from the last, so every frame is a filter
keyframe that seeds its new pixels) gives the filter's worst case per frame.
"""

from __future__ import annotations

import statistics
import time

import cv2
import numpy as np
import torch

from ..data.sequence import Sequence
from ..metrics import good_density
from ..multiview import native_cost, native_filter
from ..multiview.filter import DepthFilter
from ..multiview.filter_config import FilterConfig
from ..multiview.semidense import MultiViewConfig, estimate_semidense, select_best_fraction
from . import BenchOptions, BenchRow
from .multi_view import (
    HEIGHT,
    WIDTH,
    _keyframe_inputs,
    _median_abs_rel,
    _real_sequence,
    _synthetic_sequence,
)

TITLE = 'multi_view_filter (temporal inverse-depth filter against the per-keyframe sweep)'


def _note(extra: str = '') -> str:
    import os

    base = f'load {os.getloadavg()[0]:.1f}, {torch.get_num_threads()} torch and OpenCV threads'
    return f'{extra}; {base}' if extra else base


def stream_seconds(
    seq: Sequence, device: str, config: FilterConfig | None = None
) -> tuple[list[float], list[float], DepthFilter]:
    """Wall-clock and CPU seconds of each frame of one pass of the filter (``config``, default
    the defaults) over ``seq``, synchronised on CUDA (also ``scripts/diag/cuda_profile_filter.py``)."""
    f = DepthFilter(seq.camera, config, device=device)
    wall, cpu = [], []
    for frame in seq.frames:
        gray, pose = frame.gray, frame.pose
        t0, c0 = time.perf_counter(), time.process_time()
        f.process(gray, pose)
        if f.device.type == 'cuda':
            torch.cuda.synchronize(f.device)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu, f


def _stage_rows(label: str, seq: Sequence, device: str) -> list[BenchRow]:
    """Where a filter frame's time goes: one more pass with the filter's stage clock on
    (``multiview/filter_profile.py``), per frame after the first, and each stage's share.

    ``selection``: the per-pixel tests that choose the rows a frame searches (geometry,
    REMODE and epipolar-gradient tests, the seed bracket); ``search``: the epipolar searches;
    ``update``: the posterior update and its scatter; ``propagation``: a new keyframe (its
    candidates, the warp and the hole filling); ``seed *``: the first measurements of the new
    keyframe's pixels from the previous keyframe image; ``descriptors``: the frame's matching
    descriptors; ``other``: the rest (pose tests, scene depth).
    """
    f = DepthFilter(seq.camera, device=device)
    for i, frame in enumerate(seq.frames):
        f.clock.enabled = i > 0  # the first frame only makes the first keyframe
        f.process(frame.gray, frame.pose)
    frames = max(1, len(seq) - 1)
    total = sum(f.clock.seconds.values())
    unit = 'CPU' if f.device.type == 'cpu' else 'wall, synchronised'
    return [
        BenchRow(
            f'{label}: filter stage {stage} per frame ({unit})',
            seconds / frames * 1e3,
            'ms',
            _note(f'{seconds / total:.0%} of the frame'),
        )
        for stage, seconds in sorted(f.clock.seconds.items(), key=lambda item: -item[1])
    ]


def _sweep_seconds(seq: Sequence, key: int, device: str) -> tuple[float, float]:
    """Wall-clock and CPU seconds of one sweep of keyframe ``key``."""
    args = _keyframe_inputs(seq, key)
    t0, c0 = time.perf_counter(), time.process_time()
    estimate_semidense(*args, MultiViewConfig(), device=device)
    if device.startswith('cuda'):
        torch.cuda.synchronize()
    return time.perf_counter() - t0, time.process_time() - c0


def _cost_rows(label: str, seq: Sequence, opts: BenchOptions) -> tuple[list[BenchRow], DepthFilter]:
    """Filter per frame against the sweep per keyframe: wall clock and CPU time, and their ratios.

    The filter's figure is the median over ``opts.repeats`` passes of its mean per frame
    (every frame after the first, keyframe switches included), after one warm-up pass; the
    sweep's, the median of one call after each pass. The ratios are the medians of each
    pass's ratio to the sweep timed right after it: this machine's speed drifts by tens of
    percent within a minute (the sweep of one TUM keyframe took 83-139 ms at one thread over
    seven runs in a quarter of an hour), and passes timed against sweeps timed seconds later
    carried that drift into the ratio (0.16-0.32 at one thread).
    """
    stream_seconds(seq, opts.device)  # warm-up (allocations, first descriptors)
    key = len(seq) // 2
    estimate_semidense(*_keyframe_inputs(seq, key), MultiViewConfig(), device=opts.device)  # its warm-up
    walls, cpus, sweep_walls, sweep_cpus = [], [], [], []
    for _ in range(max(1, opts.repeats)):
        wall, cpu, f = stream_seconds(seq, opts.device)
        walls.append(statistics.fmean(wall[1:]))  # the first frame only makes the first keyframe
        cpus.append(statistics.fmean(cpu[1:]))
        one_wall, one_cpu = _sweep_seconds(seq, key, opts.device)
        sweep_walls.append(one_wall)
        sweep_cpus.append(one_cpu)
    mean, mean_cpu = statistics.median(walls), statistics.median(cpus)
    sweep_wall, sweep_cpu = statistics.median(sweep_walls), statistics.median(sweep_cpus)
    ratio_wall = statistics.median(a / b for a, b in zip(walls, sweep_walls, strict=True))
    ratio_cpu = statistics.median(a / b for a, b in zip(cpus, sweep_cpus, strict=True))
    rows = [
        BenchRow(
            f'{label}: filter per frame (mean, wall)',
            mean * 1e3,
            'ms',
            _note(f'{f.stats}; {_search_code(opts.device)}'),
        ),
        BenchRow(f'{label}: filter per frame (mean, CPU)', mean_cpu * 1e3, 'ms', _note()),
        BenchRow(f'{label}: sweep per keyframe (wall, same load)', sweep_wall * 1e3, 'ms', _note()),
        BenchRow(f'{label}: sweep per keyframe (CPU)', sweep_cpu * 1e3, 'ms', _note()),
        BenchRow(
            f'{label}: filter per frame / sweep per keyframe (wall)',
            ratio_wall,
            'ratio',
            _note('median over the passes of each one against the sweep timed after it'),
        ),
        BenchRow(
            f'{label}: filter per frame / sweep per keyframe (CPU)',
            ratio_cpu,
            'ratio',
            _note('target <= 0.2; each pass against the sweep timed after it'),
        ),
    ]
    return rows + _stage_rows(label, seq, opts.device), f


#: The filter's steps by the module of their native kernel, in the order a frame runs them.
_STEPS = ('search', 'descriptors', 'choice of rows', 'bracket', 'update')


def _search_code(device: str) -> str:
    """Which code ran the searches (and the first-measurement check), the descriptors, the
    choice of rows, the seed bracket and the update of their matches: the native kernels
    (``native_cost.py``, ``native_filter.KERNELS``) or torch (OpenCV for the descriptors). Each
    is said, as a kernel may be missing alone (a compiler that refused one file: its warning
    says which)."""
    if device.startswith('cuda'):
        return 'search, descriptors, choice of rows, bracket and update: torch'
    kernels = (native_cost, *native_filter.KERNELS)
    ran = dict(zip(_STEPS, (kernel.prepare() for kernel in kernels), strict=True))
    native = [step for step in _STEPS if ran[step]]
    other = [step for step in _STEPS if not ran[step]]
    if not other:
        return f'{", ".join(_STEPS)}: native kernels'
    if not native:
        return f'{", ".join(_STEPS)}: torch (the native kernels are off or cannot run here)'
    return f'{", ".join(native)}: native kernels; {", ".join(other)}: torch (their kernels cannot run here)'


def _accuracy(depth: np.ndarray, gt: np.ndarray, selected: np.ndarray) -> tuple[float, float]:
    """Good density (AbsRel <= 10 %, of all pixels) and the selected points' median AbsRel."""
    return good_density(depth, gt), _median_abs_rel(depth, gt, selected & np.isfinite(depth))


def filter_rows(label: str, seq: Sequence, opts: BenchOptions) -> list[BenchRow]:
    """Per-frame filter cost against the per-keyframe sweep, and both methods' accuracy.

    Accuracy on the last frame, both causal: the filter after the whole stream, the sweep
    with its online neighbours (the past frames the node would have).
    """
    rows, f = _cost_rows(label, seq, opts)
    last = len(seq) - 1
    result = f.result(seq.frames[last].pose)
    gt = seq.gt_depth_working(last)
    if gt is not None:
        fraction = MultiViewConfig().select_fraction
        # stage 1 as the fusion takes it (multiview/stage1.py): every filter estimate, and
        # for comparison the best quarter by score, the sweep's rule
        good, selected = _accuracy(result.depth, gt, result.stage1_mask('auto', fraction))
        _, best_quarter = _accuracy(result.depth, gt, select_best_fraction(result, fraction))
        swept = estimate_semidense(
            *_keyframe_inputs(seq, last, 'online'), MultiViewConfig(), device=opts.device
        )
        sweep_good, sweep_selected = _accuracy(swept.depth, gt, swept.stage1_mask('auto', fraction))
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
            BenchRow(
                f'{label}: filter selected median AbsRel',
                selected,
                'ratio',
                _note('stage 1: every published estimate'),
            ),
            BenchRow(
                f'{label}: filter best 25 % by score median AbsRel',
                best_quarter,
                'ratio',
                _note("the sweep's stage-1 rule applied to the filter"),
            ),
            BenchRow(
                f'{label}: sweep selected median AbsRel',
                sweep_selected,
                'ratio',
                _note('target: filter <= this'),
            ),
        ]
    return rows


def _keyframe_stream(quick: bool) -> Sequence:
    from ..data.synthetic import render_sequence, stress_config

    return render_sequence(stress_config('keyframes', width=WIDTH, height=HEIGHT, frames=12 if quick else 24))


def run(opts: BenchOptions) -> list[BenchRow]:
    """The synthetic room, the keyframe stream (cost only), then each ``--sequence`` (its
    first frames), as ``bench.multi_view``. OpenCV runs on torch's threads, as in a node
    (``nodes/threads.py``): the pose refinement's tracking on OpenCV's own pool of one thread
    per core read 5-6 ms more CPU than wall time per frame."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(torch.get_num_threads())
    try:
        rows = filter_rows('synthetic room', _synthetic_sequence(opts.quick), opts)
        rows += _cost_rows('synthetic keyframe stream', _keyframe_stream(opts.quick), opts)[0]
        for path in opts.sequences:
            real = _real_sequence(path, opts.quick)
            rows += filter_rows(real.name, real, opts)
    finally:
        cv2.setNumThreads(before)
    return rows
