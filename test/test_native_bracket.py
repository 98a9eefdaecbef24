"""The filter's native seed bracket (``multiview/filter_bracket.c``) against torch's.

At every call of ``bracket_seeds`` in a real stream (the synthetic room at two seed radii, a
new keyframe's many seeds included: torch's dense min / max filter there, the kernel's gather)
the kernel must narrow the same intervals to the same numbers and mark the same rows; a
neighbour whose estimate is NaN must leave its pixel's interval alone, as amin / amax do; and
the kernel must decline tensors it was not written for.
"""

from __future__ import annotations

import math

import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.multiview import filter_bracket, filter_frame_update, native_bracket
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _native_or_skip() -> None:
    if native_bracket._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _room():
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    return render_sequence(SynthConfig(width=160, height=120, frames=12, seed=4, parallax='high'))


def _compare_every_call(monkeypatch, spoil=None) -> dict[str, int]:
    calls = {'calls': 0, 'bracketed': 0}

    def both(filt, key, rows, seeds, fresh, a_r, b, lo, hi):
        if spoil is not None:
            spoil(key)
        lo_t, hi_t = lo.clone(), hi.clone()
        mine = filter_bracket.bracket_seeds(filt, key, rows, seeds, fresh, a_r, b, lo, hi)
        with monkeypatch.context() as off:
            off.setattr(filter_bracket, 'native_bracket', lambda *args: (False, None))
            theirs = filter_bracket.bracket_seeds(filt, key, rows, seeds, fresh, a_r, b, lo_t, hi_t)
        assert torch.equal(lo, lo_t) and torch.equal(hi, hi_t)
        # None and a mask of no row are the same bracket (no edge test to make)
        marked = (lambda use: 0 if use is None else int(use.sum()))(mine)
        assert marked == (0 if theirs is None else int(theirs.sum()))
        if marked:
            assert torch.equal(mine, theirs)
        calls['calls'] += 1
        calls['bracketed'] += marked
        return mine

    monkeypatch.setattr(filter_frame_update, 'bracket_seeds', both)
    return calls


@pytest.mark.parametrize('radius', [3, 1])
def test_every_bracket_of_a_stream_is_the_torch_bracket(monkeypatch, radius):
    _native_or_skip()
    calls = _compare_every_call(monkeypatch)
    seq = _room()
    filt = DepthFilter(seq.camera, FilterConfig(seed_radius=radius), device='cpu')
    for frame in seq.frames:
        filt.process(frame.gray, frame.pose)
    assert calls['calls'] >= 5 and calls['bracketed'] >= 100


def test_a_nan_neighbour_leaves_the_interval_alone(monkeypatch):
    """A measured neighbour whose mean is NaN makes torch's window minimum NaN, and the pixel is
    searched over its whole interval; the kernel does the same."""
    _native_or_skip()

    def spoil(key):
        measured = torch.nonzero(key.updates > 0).flatten()
        key.state.mu[measured[::7]] = math.nan

    calls = _compare_every_call(monkeypatch, spoil)
    seq = _room()
    filt = DepthFilter(seq.camera, None, device='cpu')
    for frame in seq.frames[:6]:
        filt.process(frame.gray, frame.pose)
    assert calls['calls'] >= 2


def test_the_kernel_declines_what_it_was_not_written_for():
    _native_or_skip()
    seq = _room()
    filt = DepthFilter(seq.camera, None, device='cpu')
    for frame in seq.frames[:3]:
        filt.process(frame.gray, frame.pose)
    key = filt.key
    rows = torch.arange(10)
    seeds = torch.arange(5)
    a_r = torch.zeros(3, 10)
    lo, hi = torch.zeros(10), torch.ones(10)
    b = (0.1, 0.0, 0.0)
    assert native_bracket.native_bracket(filt, key, rows, seeds, a_r, b, lo, hi)[0]
    for bad in (
        (rows.int(), seeds, a_r, lo, hi),  # int32 rows
        (rows, seeds, a_r[:, :9], lo, hi),  # too few rays
        (rows, seeds, a_r, lo[:9], hi),  # a short interval
        (rows, seeds, a_r.double(), lo, hi),  # doubles
    ):
        r, s, a, lo_b, hi_b = bad
        assert native_bracket.native_bracket(filt, key, r, s, a, b, lo_b, hi_b) == (False, None)
