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

from pathlib import Path

import numpy as np
import pytest
from foreign_harness import missing_tools, record, replay
from native_calls import filter_end_state
from test_native_matching_cost import _inputs as cost_inputs
from test_native_sweep_scores import _volume

from depth_fusion_ros import native_build
from depth_fusion_ros.fusion import native_halo, occlusion
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe
from depth_fusion_ros.multiview import native_choose, native_cost, native_descriptors, native_scores

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _library_or_skip(module):
    why = missing_tools()
    if why is not None:
        pytest.skip(f'cannot run aarch64 code here: {why}')
    lib = module._library()
    if lib is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')
    return lib


def _same_on_aarch64(
    monkeypatch, tmp_path: Path, module, source: str, name: str, buffers, run, last: int = 0
):
    """Record ``name``'s calls while ``run()`` runs (the last ``last`` of them; 0: all), replay
    each with ``source`` built for aarch64, and hold every buffer to this machine's values."""
    lib = _library_or_skip(module)
    argtypes = getattr(lib, name).argtypes
    calls = record(monkeypatch, lib, name, buffers)
    run()
    assert calls, f'{name} was not called'
    for k, call in enumerate(calls[-last:] if last else calls):
        workdir = tmp_path / f'{name}_{k}'
        workdir.mkdir()
        theirs = replay(Path(module.__file__).with_name(source), name, argtypes, call, workdir)
        for index in call.after:
            assert call.same_values(index, theirs[index]), f'{name}: argument {index} differs on aarch64'


F32, I32, I64, U8 = np.float32, np.int32, np.int64, np.uint8


def test_the_halo_test_on_aarch64_marks_the_same_points(monkeypatch, tmp_path):
    def buffers(a):
        n, hw = a[7], a[0] * a[1]
        return {**{i: (F32, hw) for i in range(2, 7)}, 8: (I64, n), 9: (I64, n), 10: (F32, n), 18: (U8, n)}

    def run():
        image, single, m, points = rendered_halo_keyframe(width=160, height=120, point_share=0.6)
        assert occlusion.halo_points(image, single, m, points).any()

    _same_on_aarch64(monkeypatch, tmp_path, native_halo, 'halo_test.c', 'halo_test', buffers, run)


def test_the_sweep_scores_on_aarch64_are_the_same(monkeypatch, tmp_path):
    def buffers(a):
        m, s = a[2], a[3]
        return {0: (F32, m * s), 1: (F32, m * s), 6: (F32, m), 7: (I64, m), 8: (F32, m)}

    def run():
        cost, count = _volume(600, 40, seed=3)  # unseen samples, rows seen nowhere, ties, NaN
        assert native_scores.native_coarse_scores(cost, count, 1.5, 2) is not None

    _same_on_aarch64(monkeypatch, tmp_path, native_scores, 'sweep_scores.c', 'sweep_scores', buffers, run)


def test_the_filters_choice_of_rows_on_aarch64_is_the_same(monkeypatch, tmp_path):
    def buffers(a):
        m = a[0]
        ins = {1: (F32, m), 2: (F32, m), 3: (F32, m), 4: (F32, m), 5: (U8, m), 6: (U8, m), 7: (I64, m)}
        outs = {24: (F32, 3 * m), 25: (F32, m), 26: (F32, m), 27: (U8, m), 28: (I64, m), 29: (I64, 3)}
        return {**ins, 8: (F32, 2 * m), 9: (F32, 9), **outs}

    run = lambda: filter_end_state(6)  # noqa: E731
    _same_on_aarch64(
        monkeypatch, tmp_path, native_choose, 'filter_choose.c', 'filter_choose', buffers, run, 2
    )


def test_the_matching_cost_on_aarch64_is_the_same(monkeypatch, tmp_path):
    def buffers(a):
        h, w, c, ks, as_, rs, s, r = a[1], a[2], a[3], a[5], a[7], a[12], a[13], a[14]
        table, keys, rays = (h * w + 1) * 8, (c - 1) * ks + r, 2 * as_ + r
        return {0: (F32, table), 4: (F32, keys), 6: (F32, rays), 11: (F32, s * rs), 15: (F32, s * r)}

    def run():
        key, desc, a, b, rho = cost_inputs(136, 11, seed=8)  # rows sliced, corners outside, NaN samples
        assert native_cost.native_frame_cost(key, desc, a, b, rho) is not None

    _same_on_aarch64(monkeypatch, tmp_path, native_cost, 'matching_cost.c', 'frame_cost', buffers, run)


def test_the_frame_descriptors_on_aarch64_are_the_same(monkeypatch, tmp_path):
    def buffers(a):
        hw = a[0] * a[1]
        return {2: (F32, hw), 4: (F32, a[3]), 5: (I32, 9), 6: (I32, 9), 9: (F32, 72), 12: (F32, (hw + 1) * 8)}

    run = lambda: filter_end_state(3)  # noqa: E731
    _same_on_aarch64(
        monkeypatch, tmp_path, native_descriptors, 'describe_table.c', 'describe_table', buffers, run, 1
    )
