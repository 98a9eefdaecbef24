"""Kernels and GPU busy time per frame of the temporal filter (and the fusion kernels) on CUDA.

    python scripts/diag/cuda_profile_filter.py

``torch.profiler`` over the filter's frames of the bench's synthetic room (after two warm-up
passes), and over a fast and an exact fusion of one keyframe: CUDA kernel launches per frame,
the GPU's busy time (sum of kernel durations) against the frame's wall time, and the top
kernels. What it tells: whether a stage is launch-bound (busy << wall), the issue 13 question.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

from depth_fusion_ros.bench.multi_view import _synthetic_sequence
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.multiview.filter import DepthFilter


def _kernels(prof: profile) -> tuple[int, float, list[tuple[str, float]]]:
    """Kernel count, summed device time (ms) and the five costliest kernels."""
    events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    total = sum(e.device_time for e in events) / 1e3
    by_name: dict[str, float] = {}
    for e in events:
        by_name[e.name] = by_name.get(e.name, 0.0) + e.device_time / 1e3
    top = sorted(by_name.items(), key=lambda kv: -kv[1])[:5]
    return len(events), total, top


def filter_profile() -> None:
    seq = _synthetic_sequence(False)
    for _ in range(2):  # warm-up: allocator, cuDNN/cuBLAS handles
        f = DepthFilter(seq.camera, device='cuda')
        for frame in seq.frames:
            f.process(frame.gray, frame.pose)
    torch.cuda.synchronize()
    f = DepthFilter(seq.camera, device='cuda')
    start = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for frame in seq.frames:
            f.process(frame.gray, frame.pose)
        torch.cuda.synchronize()
    wall = (time.perf_counter() - start) * 1e3 / len(seq.frames)
    n, busy, top = _kernels(prof)
    frames = len(seq.frames)
    print(
        f'filter, synthetic room, {frames} frames: {n / frames:.0f} kernels/frame, '
        f'GPU busy {busy / frames:.2f} ms of {wall:.2f} ms wall per frame (profiled)'
    )
    for name, ms in top:
        print(f'    {ms / frames:7.3f} ms/frame  {name[:90]}')


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
    print(torch.__version__, torch.cuda.get_device_name(0))
    filter_profile()
    fusion_profile()
