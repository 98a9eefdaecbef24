"""The plain C kernels built for aarch64 (an ARM robot computer) give this machine's numbers.

``native_build`` builds the kernels on any CPU; the CI has no ARM machine. Here calls of five
kernels are recorded on this machine (where their own tests hold them to their torch twins) and
replayed by the kernels cross-compiled for aarch64 under ``qemu-aarch64``
(``foreign_harness.py``): the matching cost (eight lookups a vector, ``simd8.h``'s vector
extensions on NEON), the frame descriptors (the same, with a square root and the transpose), the
halo test (bilinear reads with written-out FMAs, medians), the sweep's coarse scores (minima,
ties, NaN and inf) and the filter's choice of rows (the frame's geometry, ``hypot`` in double).
Every buffer must come back with this machine's values. Skipped where the cross compiler or the
emulator is missing (the CI), with the reason.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from foreign_harness import missing_tools, record, replay

from depth_fusion_ros import native_build
from depth_fusion_ros.fusion import native_halo, occlusion
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe
from depth_fusion_ros.multiview import native_choose, native_cost, native_descriptors, native_scores

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _library_or_skip(module):
    why = missing_tools()
    if why is not None:
        pytest.skip(f'cannot run aarch64 code here: {why}')
    lib = (module._load if module is native_cost else module._library)()
    if lib is None:
        pytest.skip(f'the native kernel cannot run here: {native_build._unsupported() or "it did not build"}')
    return lib


def _replayed_alike(tmp_path: Path, source: Path, name: str, argtypes: list, calls: list) -> None:
    assert calls, f'{name} was not called'
    for k, call in enumerate(calls):
        workdir = tmp_path / f'{name}_{k}'
        workdir.mkdir()
        theirs = replay(source, name, argtypes, call, workdir)
        for index in call.after:
            assert call.same_values(index, theirs[index]), f'{name}: argument {index} differs on aarch64'


def test_the_halo_test_on_aarch64_marks_the_same_points(monkeypatch, tmp_path):
    lib = _library_or_skip(native_halo)
    argtypes = lib.halo_test.argtypes
    f32, i64 = np.float32, np.int64
    planes = {i: (f32, 0) for i in range(2, 7)}

    def buffers(a):
        n, hw = a[7], a[0] * a[1]
        return {**{i: (f32, hw) for i in planes}, 8: (i64, n), 9: (i64, n), 10: (f32, n), 18: (np.uint8, n)}

    calls = record(monkeypatch, lib, 'halo_test', buffers)
    image, single, m, points = rendered_halo_keyframe(width=160, height=120, point_share=0.6)
    assert occlusion.halo_points(image, single, m, points).any()
    source = Path(native_halo.__file__).with_name('halo_test.c')
    _replayed_alike(tmp_path, source, 'halo_test', argtypes, calls)


def test_the_sweep_scores_on_aarch64_are_the_same(monkeypatch, tmp_path):
    lib = _library_or_skip(native_scores)
    argtypes = lib.sweep_scores.argtypes
    f32, i64 = np.float32, np.int64

    def buffers(a):
        m, s = a[2], a[3]
        return {0: (f32, m * s), 1: (f32, m * s), 6: (f32, m), 7: (i64, m), 8: (f32, m)}

    calls = record(monkeypatch, lib, 'sweep_scores', buffers)
    gen = torch.Generator().manual_seed(3)
    cost = torch.rand(600, 40, generator=gen) * 2.0
    cost[cost < 0.04] = math.inf
    cost[::97, 3] = math.nan
    cost[::50] = math.inf
    cost[1::50] = 0.5
    count = torch.rand(600, 40, generator=gen) * 4.0
    count[::31] = math.nan
    assert native_scores.native_coarse_scores(cost, count, 1.5, 2) is not None
    source = Path(native_scores.__file__).with_name('sweep_scores.c')
    _replayed_alike(tmp_path, source, 'sweep_scores', argtypes, calls)


def test_the_filters_choice_of_rows_on_aarch64_is_the_same(monkeypatch, tmp_path):
    lib = _library_or_skip(native_choose)
    argtypes = lib.filter_choose.argtypes
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
    from depth_fusion_ros.multiview.filter import DepthFilter

    f32, i64, u8 = np.float32, np.int64, np.uint8

    def buffers(a):
        m = a[0]
        ins = {1: (f32, m), 2: (f32, m), 3: (f32, m), 4: (f32, m), 5: (u8, m), 6: (u8, m), 7: (i64, m)}
        outs = {24: (f32, 3 * m), 25: (f32, m), 26: (f32, m), 27: (u8, m), 28: (i64, m), 29: (i64, 3)}
        return {**ins, 8: (f32, 2 * m), 9: (f32, 9), **outs}

    calls = record(monkeypatch, lib, 'filter_choose', buffers)
    seq = render_sequence(SynthConfig(width=160, height=120, frames=6, seed=4, parallax='high'))
    filt = DepthFilter(seq.camera, None, device='cpu')
    for frame in seq.frames:
        filt.process(frame.gray, frame.pose)
    source = Path(native_choose.__file__).with_name('filter_choose.c')
    _replayed_alike(tmp_path, source, 'filter_choose', argtypes, calls[-2:])


def test_the_matching_cost_on_aarch64_is_the_same(monkeypatch, tmp_path):
    lib = _library_or_skip(native_cost)
    argtypes = lib.frame_cost.argtypes
    f32 = np.float32

    def buffers(a):
        h, w, c, ks, as_, rs, s, r = a[1], a[2], a[3], a[5], a[7], a[12], a[13], a[14]
        table, keys, rays = (h * w + 1) * 8, (c - 1) * ks + r, 2 * as_ + r
        return {0: (f32, table), 4: (f32, keys), 6: (f32, rays), 11: (f32, s * rs), 15: (f32, s * r)}

    calls = record(monkeypatch, lib, 'frame_cost', buffers)
    gen = torch.Generator().manual_seed(8)
    desc = torch.randn(1, 7, 24, 40, generator=gen)
    desc[0, 6] = 0.0
    desc[0, 6, 3:-3, 3:-3] = 1.0
    key = torch.randn(6, 150, generator=gen)[:, 5:141]
    a = torch.rand(3, 150, generator=gen)[:, 5:141]
    a[2] = a[2] * 0.5 + 0.5
    a[:2] = (a[:2] * 2.4 - 1.2) * a[2]
    a[2, 3::10] = -1.0
    rho = (torch.rand(11, 136, generator=gen) * 3.0).contiguous()
    rho[0, ::13] = math.nan
    rho[-1, 1::7] = 1e9
    assert native_cost.native_frame_cost(key, desc, a, torch.tensor([0.04, -0.02, 0.05]), rho) is not None
    source = Path(native_cost.__file__).with_name('matching_cost.c')
    _replayed_alike(tmp_path, source, 'frame_cost', argtypes, calls)


def test_the_frame_descriptors_on_aarch64_are_the_same(monkeypatch, tmp_path):
    lib = _library_or_skip(native_descriptors)
    argtypes = lib.describe_table.argtypes
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
    from depth_fusion_ros.multiview.filter import DepthFilter

    f32, i32 = np.float32, np.int32

    def buffers(a):
        hw = a[0] * a[1]
        return {2: (f32, hw), 4: (f32, a[3]), 5: (i32, 9), 6: (i32, 9), 9: (f32, 72), 12: (f32, (hw + 1) * 8)}

    calls = record(monkeypatch, lib, 'describe_table', buffers)
    seq = render_sequence(SynthConfig(width=160, height=120, frames=3, seed=4, parallax='high'))
    filt = DepthFilter(seq.camera, None, device='cpu')
    for frame in seq.frames:
        filt.process(frame.gray, frame.pose)
    source = Path(native_descriptors.__file__).with_name('describe_table.c')
    _replayed_alike(tmp_path, source, 'describe_table', argtypes, calls[-1:])
