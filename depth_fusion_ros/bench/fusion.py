"""Fusion benchmark: exact and fast interpolation time per keyframe, RANSAC time, memory.

Synthetic planes and boxes at the working resolution (320x240) with |Ω| = 2000 points, the
issue's reference load; the targets are exact ≤ 1 s per keyframe and fast ≥ 20 Hz on 2 CPU
cores. Each figure is the median of ``repeats`` runs after a warm-up (which, for the
compiled kernel, includes the one-off ``torch.compile``; reported separately). The machine
load (1-minute load average) and torch's thread count are in the notes: on a shared machine
the figures move with it.
"""

from __future__ import annotations

import multiprocessing
import os
import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np
import torch

from ..fusion.interpolation import interpolate
from ..fusion.kernel_compile import kernel_source
from ..fusion.occlusion import halo_points
from ..fusion.scenes import planes_and_boxes
from ..fusion.selection import fit_ransac
from ..fusion.weights import WeightParams
from . import BenchOptions, BenchRow

TITLE = 'fusion (weighted interpolation, RANSAC selection)'

WIDTH, HEIGHT = 320, 240
N_POINTS = 2000
#: Multi-view points a keyframe gives the halo test: the filter's stage-1 points on TUM (about
#: 21k of 76.8k pixels), the test's heaviest real load.
HALO_POINTS = 21000


def _scene(width: int, height: int, n_points: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """True depth, a distorted single-view depth, multi-view points and Ω."""
    rng = np.random.default_rng(seed)
    depth = planes_and_boxes(width, height, boxes=3, seed=seed)
    yy, xx = np.mgrid[0:height, 0:width]
    warp = 1.0 + 0.1 * np.sin(xx / width * 3.0) * np.cos(yy / height * 2.0)
    single = (0.9 * depth * warp + 0.1 + rng.normal(0, 0.01, depth.shape)).astype(np.float32)
    omega = np.zeros(depth.shape, dtype=bool)
    omega.ravel()[rng.choice(depth.size, size=min(n_points, depth.size), replace=False)] = True
    multi = np.where(omega, depth, np.nan).astype(np.float32)
    return depth, single, multi, omega


def _timed(fn: Callable[[], object], repeats: int, warmup: int = 0) -> tuple[float, float]:
    """(first call, median of ``repeats`` further calls after ``warmup`` untimed ones) in seconds.

    On CUDA the calls after the first still meet kernels used for the first time (the fast
    mode's fix-up chunks have their own shapes): on an H200, 2026-11-27, three repeats right
    after the first call gave a fast compiled median of 7.7 ms where 30 after three warm-up
    calls gave 3.4 ms (docs/performance.md "GPU"), so the CUDA rows warm up twice more."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times)


def _note(extra: str = '') -> str:
    load = os.getloadavg()[0]
    base = f'load {load:.1f} on {os.cpu_count()} cores, {torch.get_num_threads()} torch threads'
    return f'{extra}; {base}' if extra else base


def run(opts: BenchOptions) -> list[BenchRow]:
    width, height, n_points = (
        (WIDTH // 2, HEIGHT // 2, N_POINTS // 4) if opts.quick else (WIDTH, HEIGHT, N_POINTS)
    )
    repeats = 1 if opts.quick else max(1, opts.repeats)
    depth, single, multi, omega = _scene(width, height, n_points)
    size = f'{width}x{height}, |Ω|={int(omega.sum())}'
    rows: list[BenchRow] = []
    results = {}
    default_threads = torch.get_num_threads()
    # On a CPU shared with other work, torch's OpenMP team stalls whenever one of its threads
    # is descheduled, so one thread can beat two; both are measured.
    thread_counts = sorted({1, default_threads}) if opts.device == 'cpu' else [default_threads]
    try:
        for threads in thread_counts:
            torch.set_num_threads(threads)
            for compiled in (False, True):
                tag = f'{"compiled" if compiled else "eager"}, {threads} thread{"s" if threads > 1 else ""}'
                for mode in ('exact', 'fast'):

                    def call(mode: str = mode, compiled: bool = compiled) -> None:
                        results[(mode, compiled)] = interpolate(
                            single, multi, omega, mode=mode, device=opts.device, compile_kernel=compiled
                        )

                    first, median = _timed(call, repeats, warmup=2 if opts.device.startswith('cuda') else 0)
                    what = f'{size}; {kernel_source(WeightParams(), opts.device)}' if compiled else size
                    rows.append(BenchRow(f'{mode} {tag}: s/keyframe', median, 's', _note(what)))
                    if mode == 'exact':
                        pairs = float(np.isfinite(single).sum()) * int(omega.sum())
                        # wall time x threads per weight: the kernel's cost independent of threading
                        per_pair = median / pairs * 1e9 * threads
                        note = f'{pairs:.3g} weights (pixels x |Ω|)'
                        rows.append(BenchRow(f'exact {tag}: ns x threads per weight', per_pair, 'ns', note))
                    if mode == 'fast':
                        rows.append(BenchRow(f'fast {tag}: keyframes/s', 1.0 / median, 'Hz', size))
                    if compiled and threads == thread_counts[0]:
                        rows.append(BenchRow(f'{mode} compiled: first call (compiles)', first, 's', size))
    finally:
        torch.set_num_threads(default_threads)

    exact, fast = results[('exact', True)], results[('fast', True)]
    eager = results[('exact', False)]
    rows.append(
        BenchRow(
            'compiled vs eager: max |offset difference|',
            float(np.nanmax(np.abs(exact.offset - eager.offset))),
            'm',
            size,
        )
    )
    mae_exact = float(np.nanmean(np.abs(single + exact.offset - depth)))
    mae_fast = float(np.nanmean(np.abs(single + fast.offset - depth)))
    rows.append(
        BenchRow(
            'fast vs exact: mean |offset difference|',
            float(np.nanmean(np.abs(fast.offset - exact.offset))),
            'm',
            size,
        )
    )
    rows.append(
        BenchRow(
            'fast vs exact: MAE difference',
            100.0 * (mae_fast - mae_exact) / mae_exact,
            '%',
            f'exact MAE {mae_exact:.4f} m, fast {mae_fast:.4f} m',
        )
    )

    rng = np.random.default_rng(1)
    s_pts = rng.uniform(0.5, 4.0, 5000)
    m_pts = 1.2 * s_pts + 0.1 + rng.normal(0, 0.02, s_pts.size)
    m_pts[: s_pts.size // 3] += rng.uniform(0.5, 2.0, s_pts.size // 3)
    _, ransac = _timed(lambda: fit_ransac(s_pts, m_pts), repeats)
    rows.append(BenchRow('RANSAC stage 2: s/keyframe', ransac, 's', '5000 stage-1 points, 200 hypotheses'))
    n_halo_points = HALO_POINTS // 4 if opts.quick else HALO_POINTS
    rows.append(_halo_row(width, height, n_halo_points, repeats, opts.device))

    if not opts.quick:
        rows.append(_memory_row(width, height, opts.device))
    return rows


def _halo_row(width: int, height: int, n_points: int, repeats: int, device: str) -> BenchRow:
    """The silhouette-halo test (``fusion/occlusion.py``: NumPy and OpenCV on the CPU, torch on a
    GPU, ``occlusion_gpu.py``) on the box scene, its image the depth's own edges under a random
    texture and its multi-view depth the true one fattened by 2 px (the near side's minimum over
    5x5 pixels, a matcher's halo), so that the test finds halos and runs all five of its steps."""
    depth, single, _, omega = _scene(width, height, n_points, seed=2)
    rng = np.random.default_rng(2)
    image = np.clip(40.0 * depth + rng.normal(0.0, 8.0, depth.shape), 0, 255).astype(np.float32)
    fattened = cv2.erode(depth.astype(np.float32), np.ones((5, 5), np.uint8))
    multi = np.where(omega, fattened, np.nan).astype(np.float32)
    halo = halo_points(image, single, multi, omega, device=device)
    wrong = omega & (np.abs(fattened / depth - 1.0) > 0.1)
    warmup = 0 if device == 'cpu' else 2
    _, median = _timed(lambda: halo_points(image, single, multi, omega, device=device), repeats, warmup)
    note = (
        f'{device}, {width}x{height}, {int(omega.sum())} multi-view points; flagged {int(halo.sum())}, '
        f'{int((halo & wrong).sum())} of the {int(wrong.sum())} in the halo (off by > 10 %)'
    )
    return BenchRow('halo test: s/keyframe', median, 's', _note(note))


def _memory_row(width: int, height: int, device: str) -> BenchRow:
    """Peak resident memory of one exact interpolation with |Ω| = 20000, in a fresh process:
    Linux's peak-RSS mark (VmHWM) is reset just before the call, so the figure is what the
    fusion itself adds on top of the process (torch, the inputs)."""
    ctx = multiprocessing.get_context('spawn')
    with ctx.Pool(1) as pool:
        before, peak, seconds = pool.apply(_memory_probe, (width, height, device, 20000))
    return BenchRow(
        'exact, |Ω|=20000: peak RSS above the process',
        (peak - before) / 1024.0,
        'MB',
        f'process {before / 1024.0:.0f} MB before, {seconds:.1f} s eager, 1 thread; '
        f'load {os.getloadavg()[0]:.1f}',
    )


def _status_kb(field: str) -> int:
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith(field + ':'):
                return int(line.split()[1])
    return 0


def _memory_probe(width: int, height: int, device: str, n_points: int) -> tuple[int, int, float]:
    torch.set_num_threads(1)
    _, single, multi, omega = _scene(width, height, n_points, seed=3)
    try:
        with open('/proc/self/clear_refs', 'w') as f:
            f.write('5')  # reset VmHWM to the current RSS
    except OSError:
        pass
    before = _status_kb('VmRSS')
    t0 = time.perf_counter()
    interpolate(single, multi, omega, mode='exact', device=device)
    seconds = time.perf_counter() - t0
    return before, _status_kb('VmHWM'), seconds
