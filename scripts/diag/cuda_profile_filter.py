"""Kernels and GPU busy time per frame of the temporal filter (and the fusion kernels) on CUDA.

    python scripts/diag/cuda_profile_filter.py [--fusion]

``torch.profiler`` over the filter's frames of the bench's synthetic room (after two warm-up
passes), and over a fast and an exact fusion of one keyframe: CUDA kernel launches per frame,
the GPU's busy time (sum of kernel durations) against the frame's wall time, and the top
kernels. What it tells: whether a stage is launch-bound (busy << wall), the issue 13 question.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

from depth_fusion_ros.bench.multi_view import _synthetic_sequence
from depth_fusion_ros.bench.multi_view_filter import stream_seconds
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig


def _kernels(prof: profile) -> tuple[int, float, list[tuple[str, float]]]:
    """Kernel count, summed device time (ms) and the five costliest kernels."""
    events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    total = sum(e.device_time for e in events) / 1e3
    by_name: dict[str, float] = {}
    for e in events:
        by_name[e.name] = by_name.get(e.name, 0.0) + e.device_time / 1e3
    top = sorted(by_name.items(), key=lambda kv: -kv[1])[:5]
    return len(events), total, top


#: Host-device synchronisations: a scalar read (.item(), float(), int(), bool()), a nonzero or
#: masked select (data-dependent size), an explicit synchronise.
SYNC_OPS = ('aten::_local_scalar_dense', 'aten::nonzero', 'aten::masked_select', 'cudaStreamSynchronize')


def _syncs(prof: profile) -> dict[str, int]:
    counts = dict.fromkeys(SYNC_OPS, 0)
    for e in prof.events():
        if e.name in counts:
            counts[e.name] += 1
    return counts


DEVICE = 'cuda' if torch.cuda.is_available() else 'cpu'  # cpu: tries the script, no kernels


def _sync() -> None:
    if DEVICE == 'cuda':
        torch.cuda.synchronize()


def _frame_times(seq, config: FilterConfig) -> np.ndarray:
    """Milliseconds of every frame of one pass (the bench's own timing, first frame included)."""
    return np.array(stream_seconds(seq, DEVICE, config)[0]) * 1e3


def filter_profile(variants: dict[str, dict] | None = None) -> None:
    """Per variant of the filter's config: unprofiled wall per frame (mean and median over the
    room's frames, synchronised), then the profiled kernels, GPU busy time and host syncs."""
    seq = _synthetic_sequence(False)
    variants = variants or {'default': {}}
    for _ in range(2):  # warm-up: allocator, cuDNN/cuBLAS handles
        _frame_times(seq, FilterConfig())
    for label, fields in variants.items():
        config = FilterConfig(**fields)
        times = np.concatenate([_frame_times(seq, config) for _ in range(2)])
        f = DepthFilter(seq.camera, config, device=DEVICE)
        start = time.perf_counter()
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for frame in seq.frames:
                f.process(frame.gray, frame.pose)
            _sync()
        wall = (time.perf_counter() - start) * 1e3 / len(seq.frames)
        n, busy, top = _kernels(prof)
        frames = len(seq.frames)
        syncs = ', '.join(f'{k.split("::")[-1]} {v / frames:.1f}' for k, v in _syncs(prof).items())
        print(
            f'filter [{label}], synthetic room, {frames} frames: wall {times.mean():.2f} ms mean, '
            f'{np.median(times):.2f} median (unprofiled); {n / frames:.0f} kernels/frame, GPU busy '
            f'{busy / frames:.2f} ms of {wall:.2f} ms wall (profiled); per frame: {syncs}'
        )
        for name, ms in top[:3]:
            print(f'    {ms / frames:7.3f} ms/frame  {name[:90]}')
        if label == next(iter(variants)):
            table = prof.key_averages().table(sort_by='self_cpu_time_total', row_limit=12)
            print(table)


def fusion_profile() -> None:
    sc = make_scene(320, 240, n_points=2000)
    omega = np.isfinite(sc.multi)
    for mode in ('fast', 'exact'):
        for compiled in (False, True):
            for _ in range(3):
                interpolate(sc.single, sc.multi, omega, mode=mode, device='cuda', compile_kernel=compiled)
            torch.cuda.synchronize()
            start = time.perf_counter()
            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                interpolate(sc.single, sc.multi, omega, mode=mode, device='cuda', compile_kernel=compiled)
                torch.cuda.synchronize()
            wall = (time.perf_counter() - start) * 1e3
            n, busy, top = _kernels(prof)
            print(
                f'fusion {mode} {"compiled" if compiled else "eager"}, |omega| 2000: {n} kernels, '
                f'GPU busy {busy:.2f} ms of {wall:.2f} ms wall (profiled)'
            )
            for name, ms in top[:3]:
                print(f'    {ms:7.3f} ms  {name[:90]}')


if __name__ == '__main__':
    print(torch.__version__, torch.cuda.get_device_name(0) if DEVICE == 'cuda' else 'cpu')
    filter_profile(
        {
            'default': {},
            'reject_edge_minima off': {'reject_edge_minima': False},
            'min_published_fraction 0': {'min_published_fraction': 0.0},
        }
    )
    if '--fusion' in sys.argv:
        fusion_profile()
