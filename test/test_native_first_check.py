"""The filter's native first-measurement check (``matching_cost.c``: ``first_check``) against torch's.

At every call of ``check_first_matches`` in real streams (the synthetic room, and a striped wall
whose first matches are mostly not distinct) the kernel must change the matches, their motion,
their cost and their validity exactly as the torch code does, on one thread and split over two;
a whole stream must end in the same state; and a search the tests substitute must still be the
one that runs (the kernel then declines).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.multiview import filter as filter_module
from depth_fusion_ros.multiview import filter_first_check, filter_frame_update, native_cost
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.native_first_check import native_first_check

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _native_or_skip() -> None:
    if native_cost._load() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build._unsupported() or "it did not build"}')


def _same(mine: torch.Tensor, theirs: torch.Tensor) -> bool:
    if not mine.dtype.is_floating_point:
        return torch.equal(mine, theirs)
    return torch.equal(mine.isnan(), theirs.isnan()) and torch.equal(
        mine.nan_to_num(-7.0), theirs.nan_to_num(-7.0)
    )


def _room():
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    seq = render_sequence(SynthConfig(width=160, height=120, frames=10, seed=4, parallax='high'))
    return seq.camera, [(frame.gray, frame.pose) for frame in seq.frames]


def _stripes():
    """A wall of vertical stripes 3 px apart, the camera moving sideways: the whole-range
    searches land on neighbouring stripes, so most first matches are not distinct."""
    camera = PinholeCamera(160, 120, 120.0, 120.0, 79.5, 59.5)
    frames = []
    for k in range(20):
        pose = np.eye(4)
        pose[0, 3] = 0.02 * k
        v, u = np.mgrid[0:120, 0:160].astype(np.float64)
        x = pose[0, 3] + (u - camera.cx) * 3.0 / camera.fx
        phase = 2 * np.pi * x / (3.0 * 3.0 / camera.fx) + 0.8 * np.sin(2 * np.pi * (v - camera.cy) / 16.0)
        frames.append(((0.5 + 0.3 * np.tanh(2.5 * np.sin(phase))).astype(np.float32), pose))
    return camera, frames


@pytest.mark.parametrize('threads', [1, 2])
@pytest.mark.parametrize('scene', [_room, _stripes])
def test_every_check_of_a_stream_is_the_torch_check(monkeypatch, scene, threads):
    _native_or_skip()
    if threads > 1:  # every call split over the threads
        torch.set_num_threads(threads)
        monkeypatch.setattr(native_cost, 'THREAD_MIN_LOOKUPS', 1)
    calls = {'checked': 0, 'first': 0, 'distinct': 0}

    def both(filt, key, rows, desc, a_r, geo, x, j_x, cost, valid):
        theirs = [t.clone() for t in (x, j_x, cost, valid)]
        first = valid & (key.updates.index_select(0, rows) == 0)
        assert native_first_check(filt, key, rows, desc, a_r, geo, x, j_x, cost, valid)
        with monkeypatch.context() as off:
            off.setattr(filter_first_check, 'native_first_check', lambda *args: False)
            filter_first_check.check_first_matches(filt, key, rows, desc, a_r, geo, *theirs)
        for name, mine, other in zip(
            ('x', 'j_x', 'cost', 'valid'), (x, j_x, cost, valid), theirs, strict=True
        ):
            assert _same(mine, other), name
        calls['checked'] += 1
        calls['first'] += int(first.sum())
        calls['distinct'] += int((first & valid).sum())
        return valid

    monkeypatch.setattr(filter_frame_update, 'check_first_matches', both)
    camera, frames = scene()
    filt = DepthFilter(camera, None, device='cpu')
    for image, pose in frames:
        filt.process(image, pose)
    assert calls['checked'] >= 5 and calls['first'] >= 200
    # both outcomes checked: the room's first matches mostly distinct, the stripes' mostly not
    share = calls['distinct'] / calls['first']
    assert share > 0.5 if scene is _room else share < 0.1


def test_a_stream_ends_in_the_same_state_with_and_without_it(monkeypatch):
    _native_or_skip()
    camera, frames = _room()

    def run() -> list[torch.Tensor]:
        filt = DepthFilter(camera, None, device='cpu')
        for image, pose in frames:
            filt.process(image, pose)
        k = filt.key
        return [t.clone() for t in (k.state.mu, k.state.var, k.state.a, k.state.b, k.updates, k.cost)]

    native = run()
    monkeypatch.setattr(filter_first_check, 'native_first_check', lambda *args: False)
    plain = run()
    assert all(_same(mine, theirs) for mine, theirs in zip(native, plain, strict=True))


def test_a_substituted_search_still_runs(monkeypatch):
    """Tests count and shape the filter's searches by patching ``filter.search_interval``:
    the kernel declines then, and the check's search goes through the substitute."""
    _native_or_skip()
    camera, frames = _room()
    windows = []
    real = filter_module.search_interval

    def counting(key_desc, frame_desc, rays, lo, hi, samples, *args, **kwargs):
        windows.append(samples)
        return real(key_desc, frame_desc, rays, lo, hi, samples, *args, **kwargs)

    monkeypatch.setattr(filter_module, 'search_interval', counting)
    filt = DepthFilter(camera, None, device='cpu')
    for image, pose in frames:
        filt.process(image, pose)
    assert 2 * round(filt.config.first_check_px) + 1 in windows  # the check's own searches
