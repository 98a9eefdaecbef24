"""The native matching cost (``multiview/matching_cost.c``) against the torch code it replaces.

The kernels must give the numbers the torch code gives: the filter's per-frame cost
(``filter_search._frame_cost_torch``) and the sweep's cost and count over n neighbours
(``cost_volume.sample_cost_torch``), on rows inside and outside the image, behind the camera,
with undefined inverse depths, in slices of larger tensors and split over threads; and the
filter and the sweep must give the same depth with them and without them.
"""

from __future__ import annotations

import ctypes
import math
import subprocess

import pytest
import torch
from native_calls import filter_end_state

import depth_fusion_ros.multiview.filter_search as search
from depth_fusion_ros import native_build
from depth_fusion_ros.multiview import native_cost
from depth_fusion_ros.multiview.cost_volume import EpipolarRays, sample_cost_torch
from depth_fusion_ros.multiview.filter_search import _frame_cost_torch

pytestmark = pytest.mark.usefixtures('one_torch_thread')

WIDTH, HEIGHT = 80, 60


def _native_or_skip() -> None:
    if native_cost._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _inputs(rows: int, samples: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    desc = torch.randn(1, 7, HEIGHT, WIDTH, generator=gen)
    desc[0, 6] = 0.0
    desc[0, 6, 3:-3, 3:-3] = 1.0  # the visibility band, as patch_descriptors makes it
    # Rows of a larger (C, N) / (3, N) tensor, as the filter's buckets are slices.
    key = torch.randn(6, rows + 9, generator=gen)[:, 5 : 5 + rows]
    a = torch.rand(3, rows + 9, generator=gen)[:, 5 : 5 + rows]
    a[2] = a[2] * 0.5 + 0.5
    a[:2] = (a[:2] * 2.4 - 1.2) * a[2]  # normalised coordinates in [-1.2, 1.2] at infinity: a few outside
    a[2, 3::10] = -1.0  # behind the camera at small inverse depths: w clamped at 1e-4
    b = torch.tensor([0.04, -0.02, 0.05])
    rho = (torch.rand(samples, rows, generator=gen) * 3.0).contiguous()
    rho[0, ::13] = math.nan  # undefined samples stay undefined
    rho[-1, 1::7] = 1e9  # far outside: every corner out of the frame
    return key, desc, a, b, rho


def _compare(ours: torch.Tensor, reference: torch.Tensor) -> None:
    assert ours.shape == reference.shape
    assert torch.equal(torch.isnan(ours), torch.isnan(reference))
    assert torch.equal(torch.isinf(ours), torch.isinf(reference))
    finite = torch.isfinite(reference)
    assert finite.float().mean() > 0.3 or finite.numel() < 100
    if finite.any():
        assert float((ours[finite] - reference[finite]).abs().max()) <= 1e-5


@pytest.mark.parametrize(('rows', 'samples'), [(1, 1), (7, 3), (8, 6), (203, 11), (1000, 32)])
def test_the_native_cost_is_the_torch_cost(rows, samples):
    _native_or_skip()
    key, desc, a, b, rho = _inputs(rows, samples)
    ours = native_cost.native_frame_cost(key, desc, a, b, rho)
    assert ours is not None
    _compare(ours, _frame_cost_torch(key, desc, a, b, rho))


def test_rows_split_over_threads_give_the_same_numbers(monkeypatch):
    _native_or_skip()
    key, desc, a, b, rho = _inputs(4001, 20, seed=3)
    one = native_cost.native_frame_cost(key, desc, a, b, rho)
    monkeypatch.setattr(native_cost, 'THREAD_MIN_LOOKUPS', 1)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        split = native_cost.native_frame_cost(key, desc, a, b, rho)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(torch.isnan(one), torch.isnan(split))
    assert torch.equal(one.nan_to_num(nan=-1.0), split.nan_to_num(nan=-1.0))


@pytest.mark.parametrize(
    ('rows', 'samples', 'refine', 'distinct', 'edges'),
    [(5, 3, 1, True, True), (203, 6, 0, False, False), (203, 8, 0, False, True), (1000, 16, 0, True, True),
     (1003, 32, 2, True, True), (77, 32, 3, True, False)],
)  # fmt: skip
def test_the_native_search_is_the_torch_search(monkeypatch, rows, samples, refine, distinct, edges):
    """A bucket's whole search (coarse samples, best, distinctiveness, fine samples, parabola)
    in the kernel: each row's match, cost, ratio and verdict as the torch code gives them, bit
    for bit, with undefined intervals among them (every fifth row's; NaN stays NaN)."""
    _native_or_skip()
    key, desc, a, b, _ = _inputs(rows, 2, seed=rows)
    gen = torch.Generator().manual_seed(rows)
    lo = torch.rand(rows, generator=gen) * 2.0
    hi = lo + torch.rand(rows, generator=gen) * 0.5
    lo[::5] = math.nan
    args = (key, desc, (a, b), lo, hi, samples, refine, 1 << 22, distinct, edges)
    ours = search.search_interval(*args)
    monkeypatch.setattr(search, 'native_frame_search', lambda *args: None)
    theirs = search.search_interval(*args)
    assert (bool(theirs.ok.any()) or rows < 10) and not bool(theirs.ok.all())
    assert torch.equal(ours.ok, theirs.ok)
    for name in ('rho', 'cost', 'distinct'):
        mine, reference = getattr(ours, name), getattr(theirs, name)
        assert torch.equal(mine.nan_to_num(nan=-7.0), reference.nan_to_num(nan=-7.0)), name
        assert torch.equal(mine.isnan(), reference.isnan()), name


def test_the_native_search_splits_rows_over_threads_alike(monkeypatch):
    _native_or_skip()
    key, desc, a, b, _ = _inputs(4001, 2, seed=9)
    lo = torch.rand(4001, generator=torch.Generator().manual_seed(9)) * 2.0
    args = (key, desc, a, b, lo, lo + 0.3, 32, 2, True, True)
    one = native_cost.native_frame_search(*args)
    monkeypatch.setattr(native_cost, 'THREAD_MIN_LOOKUPS', 1)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        split = native_cost.native_frame_search(*args)
    finally:
        torch.set_num_threads(before)
    for mine, theirs in zip(one, split, strict=True):
        assert torch.equal(mine.isnan(), theirs.isnan())
        assert torch.equal(mine.nan_to_num(nan=-7.0), theirs.nan_to_num(nan=-7.0))


@pytest.mark.parametrize(
    ('n', 'channels', 'height', 'width'),
    [(1, 7, 60, 80), (4, 5, 7, 9), (2, 8, 3, 3), (1, 7, 1, 9), (2, 5, 6, 1)],
)
def test_the_descriptor_table_is_the_channels_last_copy(monkeypatch, n, channels, height, width):
    """The table the kernels read: each pixel's channels then zeros, a zero block after each
    image; from a fresh buffer and from a reused one (a dropped table's, full of old values)."""
    _native_or_skip()
    from collections import OrderedDict

    monkeypatch.setattr(native_cost, '_tables', OrderedDict())
    monkeypatch.setattr(native_cost, '_spares', {})
    lib = native_cost._library()
    shape = (n, height * width + 1, native_cost.LANES)
    for seed in (1, 2):
        desc = torch.randn(n, channels, height, width, generator=torch.Generator().manual_seed(seed))
        if seed == 2:  # interleaved channels, as the filter's frame descriptors come
            desc = desc.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
        if 1 in (height, width):  # a size-1 dimension's stride is free (torch ignores it): a strange one
            odd = [st if size > 1 else 12345 for st, size in zip(desc.stride(), desc.shape, strict=True)]
            desc = desc.as_strided(desc.shape, odd)
        expected = torch.zeros(shape)
        expected[:, :-1, :channels] = desc.permute(0, 2, 3, 1).reshape(n, height * width, channels)
        table = native_cost._channels_last(lib, desc)
        assert torch.equal(table, expected)
        assert shape not in native_cost._spares  # the second one took the first one's memory
        held = table
        del table
        native_cost._keep_spare(native_cost._tables.pop(id(desc))[2])
        assert shape not in native_cost._spares  # still held here: not reused
        del held
        native_cost._tables[id(desc)] = (desc, desc._version, native_cost._channels_last(lib, desc))
        native_cost._keep_spare(native_cost._tables.pop(id(desc))[2])
        assert shape in native_cost._spares


def test_the_cpu_descriptors_are_the_table_itself():
    """The filter's CPU descriptors are written as the kernels' table (``native_descriptors``):
    the kernels read that memory in place, and it holds what the copy would (the channels,
    zeros after them, a zero block after the image). A tensor of that layout without its zero
    block is copied, not read past its end or with a corner that is not zero."""
    _native_or_skip()
    from depth_fusion_ros.multiview.descriptors import patch_descriptors

    gen = torch.Generator().manual_seed(3)
    images = torch.rand(1, HEIGHT, WIDTH, generator=gen)
    desc = patch_descriptors(images, visibility_margin=3, channels=6, channels_last=True)
    assert desc.shape == (1, 7, HEIGHT, WIDTH)
    lib = native_cost._library()
    table = native_cost._channels_last(lib, desc)
    assert table.data_ptr() == desc.data_ptr()  # no copy
    expected = torch.zeros(1, HEIGHT * WIDTH + 1, native_cost.LANES)
    expected[:, :-1, :7] = desc.permute(0, 2, 3, 1).reshape(1, HEIGHT * WIDTH, 7)
    assert torch.equal(table, expected)
    planar = patch_descriptors(images, visibility_margin=3, channels=6)
    # the planar layout's numbers (OpenCV's), to float32 rounding: the native descriptors sum
    # in another order (test_native_descriptors.py)
    assert torch.allclose(desc, planar, rtol=0.0, atol=1e-5)
    spoiled = desc.as_strided((1, HEIGHT * WIDTH + 1, native_cost.LANES), ((HEIGHT * WIDTH + 1) * 8, 8, 1), 0)
    spoiled[0, -1, 0] = 1.0  # the zero block written to: not a table any more
    assert native_cost._table_in_place(desc) is None
    copied = native_cost._channels_last(lib, desc)
    assert copied.data_ptr() != desc.data_ptr()
    assert torch.equal(copied, expected)


def test_descriptors_made_under_inference_mode_are_looked_up_too():
    """Inference tensors have no version counter (the table cache's test of an in-place
    change): their table is made for each call instead, and the numbers are the same."""
    _native_or_skip()
    key, desc, a, b, rho = _inputs(203, 11)
    expected = _frame_cost_torch(key, desc, a, b, rho)
    with torch.inference_mode():
        frozen = desc.clone()
        assert frozen.is_inference()
        first = native_cost.native_frame_cost(key, frozen, a, b, rho)
        frozen[:, :6].mul_(-1.0)  # the descriptors changed in place, unseen by any version counter
        second = native_cost.native_frame_cost(key, frozen, a, b, rho)
    _compare(first, expected)
    flipped = desc.clone()
    flipped[:, :6] *= -1.0
    _compare(second, _frame_cost_torch(key, flipped, a, b, rho))


def test_the_kernel_declines_what_it_was_not_written_for():
    """More than seven channels, another dtype: None, and the caller's torch code runs."""
    key, desc, a, b, rho = _inputs(50, 4)
    wide = torch.cat((desc, desc[:, :2]), dim=1)
    assert native_cost.native_frame_cost(torch.cat((key, key[:2])), wide, a, b, rho) is None
    doubles = (t.double() for t in (key, desc, a, b, rho))
    assert native_cost.native_frame_cost(*doubles) is None
    lo = torch.zeros(50)
    too_many = native_cost.SEARCH_MAX_SAMPLES + 1
    assert native_cost.native_frame_search(key, desc, a, b, lo, lo + 1, too_many, 2, True, True) is None


def test_the_kernels_build_wherever_they_can_run():
    """A machine the kernels are written for (x86-64 with AVX2 and FMA and a C compiler, as CI)
    builds and loads them: a broken build is a failure here, not a quiet fall back to torch."""
    why = native_build.unavailable()
    if why is not None:
        pytest.skip(f'not written for this machine: {why}')
    assert native_cost.prepare()


def test_a_compiler_without_openmp_builds_them_single_threaded(monkeypatch, tmp_path):
    """A compiler that refuses ``-fopenmp`` (a ``cc`` wrapper here) still gives a library, built
    without it, into the user cache; the kernel then gives the same numbers on one thread."""
    if native_build.unavailable() is not None:
        pytest.skip(f'not written for this machine: {native_build.unavailable()}')
    real = native_build._compiler()
    cc = tmp_path / 'cc'
    cc.write_text(f'#!/bin/sh\nfor a in "$@"; do [ "$a" = -fopenmp ] && exit 1; done\nexec {real} "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv('CC', str(cc))
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    monkeypatch.setattr(native_build, '_loaded', {})
    assert native_cost._library() is not None
    assert len(list((tmp_path / 'cache' / 'depth_fusion_ros' / 'native').glob('matching_cost-*.so'))) == 1
    key, desc, a, b, rho = _inputs(203, 11)
    _compare(native_cost.native_frame_cost(key, desc, a, b, rho), _frame_cost_torch(key, desc, a, b, rho))


def test_the_environment_turns_native_kernels_off(monkeypatch):
    monkeypatch.setenv('DEPTH_FUSION_NATIVE', '0')
    assert not native_build.native_enabled()
    assert native_build.unavailable() == 'DEPTH_FUSION_NATIVE=0'


def test_the_filter_ends_a_stream_in_the_same_state_with_and_without_it(monkeypatch):
    """The synthetic room through the whole filter: every estimate the same."""
    _native_or_skip()
    native = filter_end_state(10)
    monkeypatch.setattr(search, 'native_frame_cost', lambda *args: None)
    monkeypatch.setattr(search, 'native_frame_search', lambda *args: None)
    plain = filter_end_state(10)  # every native kernel of the filter off: the cost and the search
    for name, values in native.items():
        assert torch.allclose(values, plain[name], rtol=1e-5, atol=1e-6, equal_nan=True), name


def _sweep_inputs(rows: int, samples: int, neighbours: int, per_row: bool, seed: int = 5):
    gen = torch.Generator().manual_seed(seed)
    desc = torch.randn(neighbours, 7, HEIGHT, WIDTH, generator=gen)
    desc[:, 6] = 0.0
    desc[:, 6, 3:-3, 3:-3] = 1.0
    key = torch.randn(6, rows + 4, generator=gen)[:, 2 : 2 + rows]
    u = torch.rand(neighbours, rows, generator=gen) * (WIDTH * 1.3) - 0.15 * WIDTH  # some outside
    v = torch.rand(neighbours, rows, generator=gen) * (HEIGHT * 1.3) - 0.15 * HEIGHT
    a = torch.stack((u, v, torch.ones_like(u)), dim=-1)
    a[0, ::9, 2] = -1.0  # behind the first neighbour at small inverse depths
    b = torch.randn(neighbours, 3, generator=gen) * torch.tensor([20.0, 5.0, 0.2])
    rays = EpipolarRays(a, b, WIDTH, HEIGHT)
    rho = torch.rand(rows, samples, generator=gen) * 3.0 if per_row else torch.linspace(0.05, 3.0, samples)
    if per_row:
        rho[::11, 0] = math.nan
    return key, desc, rays, rho


@pytest.mark.parametrize(
    ('rows', 'samples', 'neighbours', 'per_row'),
    [(1, 1, 1, False), (5, 7, 2, True), (100, 48, 4, False), (311, 7, 4, True), (64, 13, 3, True)],
)
def test_the_native_sweep_cost_is_the_torch_cost(rows, samples, neighbours, per_row):
    """Cost and count; a handful of costs may differ in the last bit, where torch's own channel
    sum takes another order for the last elements of a tensor."""
    _native_or_skip()
    key, desc, rays, rho = _sweep_inputs(rows, samples, neighbours, per_row)
    a, b = rays._normalised()
    ours = native_cost.native_sweep_cost(key, desc, a, b, rho)
    assert ours is not None
    reference = sample_cost_torch(key, desc, rays, rho)
    for mine, theirs in zip(ours, reference, strict=True):
        assert mine.shape == theirs.shape
        assert torch.equal(torch.isnan(mine), torch.isnan(theirs))
        finite = torch.isfinite(theirs)
        assert torch.equal(finite, torch.isfinite(mine))
        if finite.any():
            largest = max(1.0, float(theirs[finite].abs().max()))
            assert float(((mine - theirs)[finite]).abs().max()) <= 1e-6 * largest


def test_the_sweep_gives_the_same_depth_with_and_without_it(monkeypatch):
    _native_or_skip()
    import numpy as np

    import depth_fusion_ros.multiview.cost_volume as cost_volume
    import depth_fusion_ros.multiview.semidense as semidense
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
    from depth_fusion_ros.multiview.neighbours import select_neighbours
    from depth_fusion_ros.multiview.semidense import MultiViewConfig, estimate_semidense

    seq = render_sequence(SynthConfig(width=160, height=120, frames=9, seed=6, parallax='high'))
    key = 4
    chosen = select_neighbours(seq.poses, key, 4, 'offline', seq.camera)
    frames = seq.frames

    def run():
        return estimate_semidense(
            frames[key].gray,
            frames[key].pose,
            [frames[i].gray for i in chosen],
            [frames[i].pose for i in chosen],
            seq.camera,
            MultiViewConfig(),
        )

    native = run()
    monkeypatch.setattr(cost_volume, 'native_sweep_cost', lambda *args: None)
    cost_from_torch = run()
    monkeypatch.setattr(semidense, 'native_coarse_scores', lambda *args: None)
    plain = run()  # every native kernel of the sweep off: the cost and the coarse scores
    both = torch.isfinite(torch.as_tensor(native.depth)) & torch.isfinite(torch.as_tensor(plain.depth))
    assert float(both.float().mean()) > 0.02
    assert torch.allclose(torch.as_tensor(native.depth)[both], torch.as_tensor(plain.depth)[both], rtol=1e-4)
    agree = torch.isfinite(torch.as_tensor(native.depth)) == torch.isfinite(torch.as_tensor(plain.depth))
    assert float(agree.float().mean()) > 0.999
    # The cost's last bits aside (above), the scores' kernel changes nothing at all.
    assert np.array_equal(cost_from_torch.depth, plain.depth, equal_nan=True)


def test_a_failed_build_is_said_by_the_compilers_error_line():
    """gcc's output ends with a caret under the source: the warning names the error instead."""
    output = (
        "x.c: In function 'f':\n"
        "x.c:3:9: error: 'NULL' undeclared (first use in this function)\n"
        '    3 |  return NULL;\n'
        '      |         ^~~~\n'
    )
    assert native_build._reason(subprocess.SubprocessError(output)) == (
        "x.c:3:9: error: 'NULL' undeclared (first use in this function)"
    )
    assert native_build._reason(subprocess.SubprocessError('cc exited with 1')) == 'cc exited with 1'
    assert native_build._reason(OSError()) == 'OSError()'


def test_a_changed_header_builds_a_new_library(monkeypatch, tmp_path):
    """The filter's kernels share ``filter_native.h``: a library is named by its source and the
    local headers it includes, so a changed header is built anew, not served from the cache."""
    if native_build.unavailable() is not None:
        pytest.skip(f'not written for this machine: {native_build.unavailable()}')
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    monkeypatch.setattr(native_build, '_loaded', {})
    source = tmp_path / 'kernel.c'
    source.write_text('#include "helper.h"\nvoid answer(int *out) { out[0] = HELPER; }\n')
    values = []
    for helper in (1, 2):
        (tmp_path / 'helper.h').write_text(f'#define HELPER {helper}\n')
        lib = native_build.load_native(source, {'answer': [ctypes.c_void_p]})
        native_build._loaded.clear()
        out = (ctypes.c_int * 1)()
        lib.answer(out)
        values.append(out[0])
    assert values == [1, 2]
    assert len(list((tmp_path / 'cache' / 'depth_fusion_ros' / 'native').glob('kernel-*.so'))) == 2
