"""Multi-view benchmark: semi-dense keyframes/s, TV seconds per keyframe, accuracy, memory bound.

The issue's reference load: 320x240 keyframes with n = 4 neighbours, default parameters;
targets are semi-dense >= 10 keyframes/s (the design card's; issue 13 raised it to >= 25) and
TV <= 3 s per keyframe on 2 CPU cores. The
scene is the synthetic room (``data.synthetic``, high parallax) and, with ``--sequence``,
the first frames of real TUM-layout folders (real images have other gradient statistics,
hence another candidate count). Each time is the median of ``repeats`` runs after a warm-up.

Every row's note carries the 1-minute load average and torch's intra-op thread count: on a
shared machine the figures move with the load. The ``1 thread`` rows repeat the semi-dense
timing with one intra-op thread, which is far more stable under load (a loaded machine
deschedules torch's second worker, and every small op then waits for it).
"""

from __future__ import annotations

import os
import resource
from collections.abc import Callable

import numpy as np
import torch

from ..data.sequence import Sequence
from ..multiview.descriptors import stage_descriptors
from ..multiview.neighbours import select_neighbours
from ..multiview.semidense import MultiViewConfig, estimate_semidense, select_best_fraction
from ..multiview.tv import TVConfig, estimate_tv
from ..multiview.views import prepare_views
from . import BenchOptions, BenchRow, median_seconds

TITLE = 'multi_view (semi-dense sweep, TV baseline; the temporal filter: multi_view_filter)'

WIDTH, HEIGHT = 320, 240
NEIGHBOURS = 4


def _note(extra: str = '') -> str:
    load = os.getloadavg()[0]
    base = f'load {load:.1f}, {torch.get_num_threads()} threads'
    return f'{extra}; {base}' if extra else base


def _synthetic_sequence(quick: bool) -> Sequence:
    from ..data.synthetic import SynthConfig, render_sequence

    return render_sequence(
        SynthConfig(width=WIDTH, height=HEIGHT, frames=12 if quick else 24, parallax='high')
    )


def _real_sequence(path: str, quick: bool) -> Sequence:
    from ..data.tum import load_tum_sequence

    return load_tum_sequence(path, width=WIDTH, height=HEIGHT, max_frames=12 if quick else 37)


def _keyframe_inputs(seq: Sequence, key: int, mode: str = 'offline') -> tuple:
    """``estimate_semidense``'s first arguments for keyframe ``key`` and its ``NEIGHBOURS``."""
    chosen = select_neighbours(seq.poses, key, NEIGHBOURS, mode, seq.camera)
    frames = seq.frames
    return (
        frames[key].gray,
        frames[key].pose,
        [frames[i].gray for i in chosen],
        [frames[i].pose for i in chosen],
        seq.camera,
    )


def _median_abs_rel(depth: np.ndarray, gt: np.ndarray | None, mask: np.ndarray) -> float:
    if gt is None:
        return float('nan')
    valid = mask & np.isfinite(gt) & (gt > 0)
    return float(np.median(np.abs(depth[valid] - gt[valid]) / gt[valid])) if valid.any() else float('nan')


def _semi_dense_rows(label: str, seq: Sequence, opts: BenchOptions) -> list[BenchRow]:
    key = len(seq) // 2
    inputs = _keyframe_inputs(seq, key)
    config = MultiViewConfig()

    def run() -> object:
        return estimate_semidense(*inputs, config, device=opts.device)

    seconds = median_seconds(run, opts.repeats)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        seconds_one = median_seconds(run, opts.repeats)
    finally:
        torch.set_num_threads(threads)
    result = estimate_semidense(*inputs, config, device=opts.device)
    profile_row = _profile_row(label, run)
    descriptors = _descriptor_seconds(inputs, config, opts)
    gt = seq.gt_depth_working(key)
    selected = select_best_fraction(result, config.select_fraction)
    return [
        BenchRow(f'{label}: semi-dense keyframes/s', 1.0 / seconds, 'kf/s', _note('target >= 25 (issue 13)')),
        BenchRow(f'{label}: semi-dense per keyframe', seconds * 1e3, 'ms', _note()),
        BenchRow(f'{label}: semi-dense keyframes/s, 1 thread', 1.0 / seconds_one, 'kf/s', _note()),
        profile_row,
        BenchRow(
            f'{label}: semi-dense descriptors per keyframe',
            descriptors * 1e3,
            'ms',
            _note(f'{1 + NEIGHBOURS} images; {100 * descriptors / seconds:.0f} % of the keyframe'),
        ),
        BenchRow(f'{label}: candidates searched', float(result.candidates.sum()), 'px', _note()),
        BenchRow(f'{label}: multi_view density', result.density, 'fraction', _note()),
        BenchRow(
            f'{label}: multi_view_selected median AbsRel',
            _median_abs_rel(result.depth, gt, selected),
            'ratio',
            _note(f'{selected.mean():.3%} of pixels selected'),
        ),
    ]


def _descriptor_seconds(inputs: tuple, config: MultiViewConfig, opts: BenchOptions) -> float:
    """Median time of the per-image stage of one keyframe (validation, upload, patch
    descriptors of the keyframe and its neighbours); the rest of the keyframe is the sweep."""
    key_gray, key_pose, grays, poses, camera = inputs

    def run() -> object:
        views = prepare_views(key_gray, key_pose, grays, poses, camera, opts.device)
        return stage_descriptors(views.grays, config)

    return median_seconds(run, opts.repeats)


def _profile_row(label: str, run: Callable[[], object]) -> BenchRow:
    """Where one keyframe's time goes: torch operator calls per keyframe and the operators
    with the largest self time (``torch.profiler``, CPU side), as shares of the total.

    On CPU the sweep's bilinear lookups (``grid_sampler_2d``: neighbours x channels x
    candidates x samples gathers) dominate; the rest is elementwise passes over the same
    (candidates x samples) grids and the per-image descriptors.
    """
    from torch.profiler import ProfilerActivity, profile

    # One thread: with two, a loaded machine's OpenMP stalls land on whichever op waits.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            run()
    finally:
        torch.set_num_threads(threads)
    ops = [e for e in prof.key_averages() if e.key.startswith('aten::')]
    total = sum(e.self_cpu_time_total for e in ops) or 1.0
    top = sorted(ops, key=lambda e: -e.self_cpu_time_total)[:4]
    shares = ', '.join(f'{e.key[6:]} {100.0 * e.self_cpu_time_total / total:.0f} %' for e in top)
    calls = sum(e.count for e in ops)
    note = _note(f'self time, 1 thread: {shares}')
    return BenchRow(f'{label}: semi-dense torch op calls per keyframe', float(calls), 'calls', note)


def _tv_rows(label: str, seq: Sequence, opts: BenchOptions) -> list[BenchRow]:
    key = len(seq) // 2
    inputs = _keyframe_inputs(seq, key)
    config = TVConfig()
    seconds = median_seconds(lambda: estimate_tv(*inputs, config, device=opts.device), 1 if opts.quick else 2)
    depth = estimate_tv(*inputs, config, device=opts.device)
    gt = seq.gt_depth_working(key)
    rows = [
        BenchRow(
            f'{label}: TV per keyframe', seconds, 's', _note(f'target <= 3; {config.iterations} iterations')
        ),
        BenchRow(
            f'{label}: TV median AbsRel',
            _median_abs_rel(depth, gt, np.ones(depth.shape, bool)),
            'ratio',
            _note(),
        ),
    ]
    if torch.device(opts.device).type == 'cuda':  # what the CUDA graph of the iterations saves
        eager = TVConfig(cuda_graph=False)
        seconds = median_seconds(
            lambda: estimate_tv(*inputs, eager, device=opts.device), 1 if opts.quick else 3
        )
        rows.append(
            BenchRow(f'{label}: TV per keyframe, eager iterations', seconds, 's', _note('no CUDA graph'))
        )
    return rows


def _memory_rows(seq: Sequence, opts: BenchOptions) -> list[BenchRow]:
    """The largest intermediate is bounded by ``chunk_elements`` whatever the sample count.

    ``ru_maxrss`` is the process's peak resident memory: its growth over a run with 16x the
    samples shows that the sample count raises the time, not the peak.
    """
    inputs = _keyframe_inputs(seq, len(seq) // 2)
    rows = []
    for samples in (48, 768):
        config = MultiViewConfig(num_samples=samples)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        seconds = median_seconds(lambda c=config: estimate_semidense(*inputs, c, device=opts.device), 1)
        grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024.0
        bound = config.chunk_elements * 4 / 2**20
        note = f'largest intermediate <= {bound:.0f} MiB; peak RSS grew {grown:.0f} MiB'
        rows.append(BenchRow(f'semi-dense with {samples} samples', seconds * 1e3, 'ms', _note(note)))
    return rows


def run(opts: BenchOptions) -> list[BenchRow]:
    synthetic = _synthetic_sequence(opts.quick)
    rows = _semi_dense_rows('synthetic room', synthetic, opts)
    for path in opts.sequences:
        real = _real_sequence(path, opts.quick)
        rows += _semi_dense_rows(real.name, real, opts)
        if not opts.quick:
            rows += _tv_rows(real.name, real, opts)
    rows += _tv_rows('synthetic room', synthetic, opts)
    if not opts.quick:
        rows += _memory_rows(synthetic, opts)
    return rows
