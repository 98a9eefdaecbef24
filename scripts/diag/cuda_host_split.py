"""Where the host time of a GPU keyframe goes: fusion (fast, exact), the TSDF map, adaptation,
and the sweep and TV with and without their CUDA graphs (``--only multi_view``).

    python scripts/diag/cuda_host_split.py [--device cuda] [--repeats 30]

Issue 13's GPU targets (fusion fast <= 2 ms, exact <= 5 ms, TSDF integration <= 2 ms) are
missed on host time, not arithmetic (docs/performance.md "GPU": the GPU is busy 0.4-1 ms of
5-6 ms). This says which host work it is. Per stage: the synchronised wall time per call
(median of ``repeats`` after warm-up), the CUDA kernels and the host synchronisations per call
(``torch.profiler``), and the Python functions that take the host time (``cProfile``, by own
time, over ``repeats`` calls; the profiler's overhead inflates them, so read them as shares).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import itertools
import pstats
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

# The filter profiler's kernel and host-sync counting (run as a script, this folder is on the path).
from cuda_profile_filter import _kernels, _syncs
from torch.profiler import ProfilerActivity, profile

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.engine import make_map


def _sync(device: str) -> None:
    if device.startswith('cuda'):
        torch.cuda.synchronize()


def _report(name: str, calls: list[Callable[[], object]], device: str) -> None:
    """Wall, kernels, syncs and the top host functions of ``calls`` (one call = one keyframe)."""
    n = len(calls)
    for call in calls[: min(3, n)]:  # warm-up: compile, allocator, handles
        call()
    times = []
    for call in calls:
        _sync(device)
        t0 = time.perf_counter()
        call()
        _sync(device)
        times.append(time.perf_counter() - t0)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith('cuda') else [])
    with profile(activities=activities) as prof:
        for call in calls:
            call()
        _sync(device)
    n_kernels, busy, _ = _kernels(prof)
    ops = [
        e
        for e in prof.events()
        if e.device_type == torch.autograd.DeviceType.CPU and e.name.startswith('aten::')
    ]
    syncs = _syncs(prof)
    print(
        f'== {name}: wall {1e3 * statistics.median(times):.2f} ms median ({1e3 * min(times):.2f}-'
        f'{1e3 * max(times):.2f}), {n_kernels / n:.0f} kernels, {len(ops) / n:.0f} aten calls, '
        f'GPU busy {busy / n:.2f} ms per call; syncs per call: '
        + ', '.join(f'{k.split("::")[-1]} {v / n:.1f}' for k, v in syncs.items())
    )
    pr = cProfile.Profile()
    pr.enable()
    for call in calls:
        call()
    _sync(device)
    pr.disable()
    out = io.StringIO()
    pstats.Stats(pr, stream=out).sort_stats('tottime').print_stats(14)
    lines = [ln for ln in out.getvalue().splitlines() if ln.strip()]
    start = next(i for i, ln in enumerate(lines) if 'ncalls' in ln)
    for ln in lines[start : start + 15]:
        print('   ', ln[:150])


def fusion(device: str, repeats: int) -> None:
    sc = make_scene(320, 240, n_points=2000)
    omega = np.isfinite(sc.multi)
    for mode in ('fast', 'exact'):
        for compiled in (True, False):

            def call(mode: str = mode, compiled: bool = compiled) -> object:
                return interpolate(
                    sc.single, sc.multi, omega, mode=mode, device=device, compile_kernel=compiled
                )

            _report(f'fusion {mode} {"compiled" if compiled else "eager"}', [call] * repeats, device)


def mapping(device: str, repeats: int) -> None:
    seq = render_sequence(SynthConfig(width=320, height=240, frames=30, seed=1))
    config = MapConfig(voxel_size=0.04, device=device)
    tsdf, _ = make_map(config)
    confidence = np.full((seq.camera.height, seq.camera.width), 0.8, np.float32)
    frames = list(enumerate(seq.frames))
    it = iter(frames * 100)

    def call() -> None:
        i, frame = next(it)
        tsdf.integrate(seq.gt_depth_working(i), frame.pose, seq.camera, confidence=confidence, rgb=frame.rgb)

    _report('map integrate (consistency test + engine)', [call] * repeats, device)
    engine = tsdf.engine

    def engine_call() -> None:
        i, frame = next(it)
        engine.integrate(
            seq.gt_depth_working(i), frame.pose, seq.camera, confidence=confidence, rgb=frame.rgb
        )

    _report('map engine.integrate alone', [engine_call] * repeats, device)


def adaptation(device: str, repeats: int) -> None:
    from depth_fusion_ros.adaptation.adapter import Adapter
    from depth_fusion_ros.adaptation.config import AdaptConfig
    from depth_fusion_ros.bench.adaptation import WARM_MAX, _samples, _warm_up

    config = AdaptConfig()
    n = max(3, repeats // 8)
    samples = _samples(WARM_MAX + 4)
    adapter = Adapter.from_spec('default', config, device)
    # The bench's own warm-up: until the replay buffer gives every update its full batch shapes.
    full = max(config.guard_keyframes, config.replay_per_step)
    warm, _ = _warm_up(adapter, samples[:WARM_MAX], full, lambda: _sync(device))
    it = itertools.cycle(samples[warm : warm + 4])
    _report(
        f'adaptation observe ({config.steps_per_keyframe} steps + guard, batch {1 + config.replay_per_step})',
        [lambda: adapter.observe(next(it))] * n,
        device,
    )


def multi_view(device: str, repeats: int) -> None:
    """The semi-dense sweep and the TV iterations replayed from CUDA graphs against eager."""
    from depth_fusion_ros.bench.multi_view import _keyframe_inputs, _synthetic_sequence
    from depth_fusion_ros.multiview.semidense import MultiViewConfig, estimate_semidense
    from depth_fusion_ros.multiview.tv import TVConfig, estimate_tv

    seq = _synthetic_sequence(quick=False)
    keys = [_keyframe_inputs(seq, k) for k in (8, 12, 16)]
    for graph in (True, False):
        config = MultiViewConfig(cuda_graph=graph)
        calls = [
            lambda i=i, c=config: estimate_semidense(*keys[i % 3], c, device=device) for i in range(repeats)
        ]
        _report(f'sweep, {"CUDA graph" if graph else "eager"}', calls, device)
    for graph in (True, False):
        tv = TVConfig(cuda_graph=graph)
        calls = [
            lambda i=i, c=tv: estimate_tv(*keys[i % 3], c, device=device) for i in range(max(6, repeats // 3))
        ]
        _report(f'TV, {"CUDA graph" if graph else "eager"} iterations', calls, device)


if __name__ == '__main__':
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--device', default='cuda' if torch.cuda.is_available() else 'cpu')
    ap.add_argument('--repeats', type=int, default=30)
    ap.add_argument('--only', default='fusion,mapping,adaptation,multi_view')
    a = ap.parse_args()
    print(torch.__version__, torch.cuda.get_device_name(0) if a.device.startswith('cuda') else 'cpu')
    if 'fusion' in a.only:
        fusion(a.device, a.repeats)
    if 'mapping' in a.only:
        mapping(a.device, a.repeats)
    if 'adaptation' in a.only:
        adaptation(a.device, a.repeats)
    if 'multi_view' in a.only:
        multi_view(a.device, a.repeats)
