"""A frame's native searches of the filter's chosen rows (``matching_cost.c``: ``filter_rows``)
against the torch code.

At every frame of real streams (the synthetic room; a keyframe stream, whose new keyframes bring
many whole-range and bracketed searches; a striped wall whose first matches are mostly not
distinct) the kernel must give each chosen row the match, its motion, its cost and its validity
the torch code gives (``search_rows``, the tests of each match, ``check_first_matches``), on one
thread and split over two, with the verify and medium buckets on and off and without the
first-measurement check; a whole stream must end in the same state; and a search the tests
substitute must still be the one that runs (the kernel then declines).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.multiview import filter as filter_module
from depth_fusion_ros.multiview import filter_frame_update, native_cost
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig

pytestmark = pytest.mark.usefixtures('one_torch_thread')

NAMES = ('x', 'j_x', 'cost', 'valid')


def _native_or_skip() -> None:
    if native_cost._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _same(mine: torch.Tensor, theirs: torch.Tensor) -> bool:
    if not mine.dtype.is_floating_point:
        return torch.equal(mine, theirs)
    return torch.equal(mine.isnan(), theirs.isnan()) and torch.equal(
        mine.nan_to_num(-7.0), theirs.nan_to_num(-7.0)
    )


def _room(stress: str | None = None):
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    size = {'width': 160, 'height': 120, 'frames': 12, 'seed': 4}
    if stress is None:
        config = SynthConfig(parallax='high', **size)
    else:
        from depth_fusion_ros.data.synthetic import stress_config

        config = stress_config(stress, **size)
    seq = render_sequence(config)
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


def _compare_every_frame(monkeypatch) -> dict[str, int]:
    """Each call of the kernel checked against the torch code on the same inputs; counts."""
    calls = {'calls': 0, 'rows': 0, 'valid': 0}
    native = filter_frame_update.native_search_rows

    def both(filt, key, desc, chosen):
        updates = key.updates.clone()
        mine = native(filt, key, desc, chosen)
        assert mine is not None
        assert torch.equal(key.updates, updates)  # nothing of the keyframe changed before the update
        copy = chosen._replace(a=chosen.a.clone(), lo=chosen.lo.clone(), hi=chosen.hi.clone())
        theirs = filter_frame_update._search_and_test(filt, key, desc, copy, '')
        for name, m, t in zip(NAMES, mine, theirs, strict=True):
            assert _same(m, t), name
        calls['calls'] += 1
        calls['rows'] += int(chosen.rows.numel())
        calls['valid'] += int(mine[3].sum())
        return mine

    monkeypatch.setattr(filter_frame_update, 'native_search_rows', both)
    return calls


@pytest.mark.parametrize('threads', [1, 2])
@pytest.mark.parametrize('scene', ['room', 'keyframes', 'stripes'])
def test_every_frame_s_searches_are_the_torch_searches(monkeypatch, scene, threads):
    _native_or_skip()
    if threads > 1:  # every search split over the threads
        torch.set_num_threads(threads)
        monkeypatch.setattr(native_cost, 'THREAD_MIN_LOOKUPS', 1)
    calls = _compare_every_frame(monkeypatch)
    if scene == 'stripes':
        camera, frames = _stripes()
    else:
        camera, frames = _room('keyframes' if scene == 'keyframes' else None)
    filt = DepthFilter(camera, None, device='cpu')
    for image, pose in frames:
        filt.process(image, pose)
    assert calls['calls'] >= 5 and calls['rows'] >= 2000
    # the stripes' first matches are never distinct: no match counts, nothing is born
    assert calls['valid'] == 0 if scene == 'stripes' else calls['valid'] > 0


@pytest.mark.parametrize(
    'config',
    [
        FilterConfig(verify_samples=0, medium_samples=0),  # two buckets only
        FilterConfig(first_check_px=0.0),  # no first-measurement check
        FilterConfig(reject_edge_minima=False, seed_radius=0),  # edges kept, nothing bracketed
    ],
)
def test_other_settings_give_the_torch_searches_too(monkeypatch, config):
    _native_or_skip()
    calls = _compare_every_frame(monkeypatch)
    camera, frames = _room()
    filt = DepthFilter(camera, config, device='cpu')
    for image, pose in frames:
        filt.process(image, pose)
    assert calls['calls'] >= 5


def test_a_stream_ends_in_the_same_state_with_and_without_it(monkeypatch):
    _native_or_skip()
    camera, frames = _room('keyframes')

    def run() -> list[torch.Tensor]:
        filt = DepthFilter(camera, None, device='cpu')
        for image, pose in frames:
            filt.process(image, pose)
        k = filt.key
        return [t.clone() for t in (k.state.mu, k.state.var, k.state.a, k.state.b, k.updates, k.cost)]

    native = run()
    monkeypatch.setattr(filter_frame_update, 'native_search_rows', lambda *args: None)
    plain = run()
    assert all(_same(mine, theirs) for mine, theirs in zip(native, plain, strict=True))


def test_a_substituted_search_still_runs(monkeypatch):
    """Tests count and shape the filter's searches by patching ``filter.search_interval``:
    the kernel declines then, and every search, the first-measurement check's included, goes
    through the substitute."""
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
    c = filt.config
    assert {c.verify_samples, c.short_samples, 2 * round(c.first_check_px) + 1} <= set(windows)
