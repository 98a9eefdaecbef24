"""Fusion benchmark: exact and fast interpolation time per keyframe, RANSAC time, memory.

Synthetic planes and boxes at the working resolution (320x240) with |Ω| = 2000 points, the
issue's reference load; the targets are exact ≤ 1 s per keyframe and fast ≥ 20 Hz on 2 CPU
cores. Each figure is the median of ``repeats`` runs after a warm-up (which, for the
compiled kernel, includes the one-off ``torch.compile``; reported separately). The machine
load (1-minute load average) and torch's thread count are in the notes: on a shared machine
the figures move with it.
"""

from __future__ import annotations

import os
import resource
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from ..fusion.interpolation import interpolate
from ..fusion.scenes import planes_and_boxes
from ..fusion.selection import fit_ransac
from . import BenchOptions, BenchRow

TITLE = 'fusion (weighted interpolation, RANSAC selection)'

WIDTH, HEIGHT = 320, 240
N_POINTS = 2000


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


def _timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(first call, median of ``repeats`` further calls) in seconds."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
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
    for compiled in (False, True):
        tag = 'compiled' if compiled else 'eager'
        for mode in ('exact', 'fast'):

            def call(mode: str = mode, compiled: bool = compiled) -> None:
                results[(mode, compiled)] = interpolate(
                    single, multi, omega, mode=mode, device=opts.device, compile_kernel=compiled
                )

            first, median = _timed(call, repeats if mode == 'fast' or not opts.quick else 1)
            rows.append(BenchRow(f'{mode} {tag}: s/keyframe', median, 's', _note(size)))
            if mode == 'fast':
                rows.append(BenchRow(f'fast {tag}: keyframes/s', 1.0 / median, 'Hz', size))
            if compiled:
                rows.append(BenchRow(f'{mode} compiled: first call (compiles)', first, 's', size))

    exact, fast = results[('exact', True)], results[('fast', True)]
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
            f'exact MAE {mae_exact:.4f} m',
        )
    )

    rng = np.random.default_rng(1)
    s_pts = rng.uniform(0.5, 4.0, 5000)
    m_pts = 1.2 * s_pts + 0.1 + rng.normal(0, 0.02, s_pts.size)
    m_pts[: s_pts.size // 3] += rng.uniform(0.5, 2.0, s_pts.size // 3)
    _, ransac = _timed(lambda: fit_ransac(s_pts, m_pts), repeats)
    rows.append(BenchRow('RANSAC stage 2: s/keyframe', ransac, 's', '5000 stage-1 points, 200 hypotheses'))

    if not opts.quick:
        rows.append(_memory_row(width, height, opts.device))
    return rows


def _memory_row(width: int, height: int, device: str) -> BenchRow:
    """Peak resident memory growth of one exact interpolation with |Ω| = 20000."""
    _, single, multi, omega = _scene(width, height, 20000, seed=3)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    interpolate(single, multi, omega, mode='exact', device=device, compile_kernel=True)
    seconds = time.perf_counter() - t0
    grown = max(0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024.0
    return BenchRow('exact, |Ω|=20000: peak RSS growth', grown, 'MB', _note(f'{seconds:.1f} s (compiled)'))
