"""The filter's native update of a frame's matches (``multiview/filter_apply.c``) against torch's.

The kernel must leave the keyframe state the torch code leaves, bit for bit: first
measurements, updates, outlier votes and resets, with and without the pose term of the
measurement variance, with no match at all and with every row matched (the dense form the
GPU runs is held to the same numbers in test_multiview_filter_exact.py), and a whole stream
through the filter must end in the same state with the kernel and without it.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.multiview import filter_matches, native_apply
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.filter_matches import Matches, apply_matches
from depth_fusion_ros.multiview.filter_update import BetaGaussian

pytestmark = pytest.mark.usefixtures('one_torch_thread')

FIELDS = ('mu', 'var', 'a', 'b', 'updates', 'prior', 'cost')


def _native_or_skip() -> None:
    if native_apply._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _keyframe(m: int, gen: torch.Generator) -> SimpleNamespace:
    prior = torch.rand(m, generator=gen) > 0.3
    a = torch.rand(m, generator=gen) * 12 + 1  # near the reset line: some rows fall below it
    b = torch.rand(m, generator=gen) * 12 + 1
    state = BetaGaussian(torch.rand(m, generator=gen) + 0.2, torch.rand(m, generator=gen) * 1e-2 + 1e-5, a, b)
    updates = torch.where(prior, torch.randint(1, 9, (m,), generator=gen), 0)
    cost = torch.where(prior, torch.rand(m, generator=gen), math.nan)
    return SimpleNamespace(state=state, updates=updates, prior=prior, cost=cost)


def _fields(key: SimpleNamespace) -> list[torch.Tensor]:
    s = key.state
    return [s.mu, s.var, s.a, s.b, key.updates, key.prior, key.cost]


def _copy(key: SimpleNamespace) -> SimpleNamespace:
    mu, var, a, b, updates, prior, cost = (t.clone() for t in _fields(key))
    return SimpleNamespace(state=BetaGaussian(mu, var, a, b), updates=updates, prior=prior, cost=cost)


def _same(mine: torch.Tensor, theirs: torch.Tensor) -> bool:
    if not mine.dtype.is_floating_point:
        return torch.equal(mine, theirs)
    same_nan = torch.equal(mine.isnan(), theirs.isnan())
    return same_nan and torch.equal(mine.nan_to_num(-7.0), theirs.nan_to_num(-7.0))


@pytest.mark.parametrize('pose_sigma', [0.0, 0.01])
@pytest.mark.parametrize(('searched', 'share_valid'), [(2500, 0.55), (3000, 0.0), (3000, 1.0), (1, 1.0)])
def test_the_native_update_is_the_torch_update(monkeypatch, pose_sigma, searched, share_valid):
    _native_or_skip()
    gen = torch.Generator().manual_seed(searched + int(100 * share_valid))
    m = 4000
    filt = SimpleNamespace(config=FilterConfig(pose_sigma=pose_sigma), rho_range=(0.1, 5.0))
    key = _keyframe(m, gen)
    rows = torch.randperm(m, generator=gen)[:searched]
    fresh = ~key.prior.index_select(0, rows)
    valid = torch.rand(searched, generator=gen) < share_valid
    x = torch.rand(searched, generator=gen) * 2 + 0.1
    j_x = torch.rand(searched, generator=gen) * 300 + 1
    cost = torch.rand(searched, generator=gen)
    native, plain = _copy(key), _copy(key)
    assert native_apply.native_apply_matches(filt, native, Matches(rows, x, j_x, cost, fresh), valid, 0.05)
    monkeypatch.setattr(filter_matches, 'native_apply_matches', lambda *args: False)
    apply_matches(filt, plain, Matches(rows, x, j_x, cost, fresh), valid, 0.05)
    for name, mine, theirs in zip(FIELDS, _fields(native), _fields(plain), strict=True):
        assert _same(mine, theirs), name
    changed = [not _same(after, before) for after, before in zip(_fields(plain), _fields(key), strict=True)]
    assert any(changed) or searched == 1


def test_a_big_stream_ends_in_the_same_state_with_and_without_the_kernel(monkeypatch):
    _native_or_skip()
    from depth_fusion_ros.bench.multi_view import _synthetic_sequence
    from depth_fusion_ros.multiview.filter import DepthFilter

    seq = _synthetic_sequence(False)
    frames = seq.frames[:12]

    def states(use_kernel: bool) -> list[list[torch.Tensor]]:
        calls = []
        kernel = native_apply.native_apply_matches

        def counted(*args):
            calls.append(1)
            return kernel(*args) if use_kernel else False

        monkeypatch.setattr(filter_matches, 'native_apply_matches', counted)
        filt = DepthFilter(seq.camera, None, device='cpu')
        out = []
        for frame in frames:
            filt.process(frame.gray, frame.pose)
            out.append([t.clone() for t in _fields(filt.key)])
        assert calls, 'the update never ran'
        return out

    with_kernel, without = states(True), states(False)
    assert int(with_kernel[-1][4].gt(0).sum()) > 1000  # estimates were made
    for frame, (mine, theirs) in enumerate(zip(with_kernel, without, strict=True)):
        for name, a, b in zip(FIELDS, mine, theirs, strict=True):
            assert _same(a, b), (frame, name)


def test_the_kernel_declines_what_it_was_not_written_for():
    _native_or_skip()
    gen = torch.Generator().manual_seed(5)
    filt = SimpleNamespace(config=FilterConfig(), rho_range=(0.1, 5.0))
    key = _keyframe(100, gen)
    key.state.mu = key.state.mu.double()  # not the filter's float32
    rows = torch.arange(10)
    matches = Matches(rows, torch.rand(10), torch.rand(10) + 1, torch.rand(10), ~key.prior[:10])
    before = _copy(key)
    assert not native_apply.native_apply_matches(filt, key, matches, torch.ones(10, dtype=torch.bool), 0.05)
    for name, mine, theirs in zip(FIELDS, _fields(key), _fields(before), strict=True):
        assert _same(mine.to(theirs.dtype), theirs), name
    # float64 matches against a float32 state: torch's update would compute in float64
    key.state.mu = key.state.mu.float()
    wide = Matches(rows, matches.x.double(), matches.j_x, matches.cost, matches.fresh)
    assert not native_apply.native_apply_matches(filt, key, wide, torch.ones(10, dtype=torch.bool), 0.05)
    # int32 rows: the kernel reads int64 indices
    narrow = Matches(rows.int(), matches.x, matches.j_x, matches.cost, matches.fresh)
    assert not native_apply.native_apply_matches(filt, key, narrow, torch.ones(10, dtype=torch.bool), 0.05)
