"""The dense loss terms on windows of the keyframes (``adaptation/window.py``).

A window takes views of the keyframe's depth-independent tensors; the warp of a window must be
the window of the whole keyframe's warp (same rays, same projection into the whole neighbour
images), the whole grid as a window must give the whole loss, and a windowed update learns.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros.adaptation.adapter import Adapter
from depth_fusion_ros.adaptation.batch import batch_loss
from depth_fusion_ros.adaptation.config import AdaptConfig
from depth_fusion_ros.adaptation.sample import Neighbour, make_sample
from depth_fusion_ros.adaptation.warp import warp_neighbours
from depth_fusion_ros.adaptation.window import Window, cut, draw_windows

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.fixture(scope='module')
def room():
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    return render_sequence(SynthConfig(width=160, height=120, frames=6, seed=5, parallax='high'))


def _sample(seq, i: int):
    gt = seq.gt_depth_working(i)
    depth = np.full(gt.shape, np.nan, np.float32)
    depth[::5, ::5] = gt[::5, ::5]
    score = np.where(np.isfinite(depth), 1.0, np.nan).astype(np.float32)
    nb = [Neighbour(seq.frames[j].rgb, seq.frames[j].pose) for j in (i - 1, i + 1)]
    f = seq.frames[i]
    return make_sample(i, f.rgb, seq.camera, depth, score, select_fraction=1.0, pose=f.pose, neighbours=nb)


def test_the_warp_of_a_window_is_the_window_of_the_whole_warp(tiny_model, room):
    adapter = Adapter.from_spec(tiny_model, AdaptConfig(photometric_window=1.0))
    prepared = adapter.prepare(_sample(room, 2))
    with torch.no_grad():
        log_depth = adapter.net(prepared.x)
    h, w = log_depth.shape[-2:]
    photo = prepared.grid(h, w).photometric
    win = Window(top=5, left=9, height=h // 2, width=w // 2)
    part = win.photometric(photo)
    depth = torch.exp(log_depth)
    whole, whole_ok = warp_neighbours(photo.neighbours, depth, photo.k, photo.t_ok, photo.rays)
    warped, ok = warp_neighbours(part.neighbours, win.of(depth), part.k, part.t_ok, part.rays)
    assert warped.shape[-2:] == (h // 2, w // 2)
    torch.testing.assert_close(warped, win.of(whole))
    assert torch.equal(ok, win.of(whole_ok)) and bool(ok.any())
    torch.testing.assert_close(part.identity, win.of(photo.identity))


def test_the_whole_grid_as_a_window_is_the_whole_loss_and_windows_cover_it(tiny_model, room):
    adapter = Adapter.from_spec(tiny_model, AdaptConfig(photometric_window=1.0))
    batch = [adapter.prepare(_sample(room, i)) for i in (1, 2, 3)]
    with torch.no_grad():
        log_depth = adapter.net(torch.cat([s.x for s in batch]))
    h, w = log_depth.shape[-2:]
    whole = batch_loss(log_depth, batch, adapter.config)
    as_window = batch_loss(log_depth, batch, adapter.config, [Window(0, 0, h, w)] * 3)
    assert float(as_window) == pytest.approx(float(whole), rel=1e-6)
    windows = draw_windows(3, (h, w), 0.5, np.random.default_rng(0))
    assert cut(log_depth, windows).shape == (3, 1, h // 2, w // 2)
    assert all(0 <= v.top <= h - h // 2 and 0 <= v.left <= w - w // 2 for v in windows)
    seen = np.zeros((h, w), bool)
    rng = np.random.default_rng(1)
    for _ in range(60):  # a keyframe's steps and replays: the windows cover all of it
        for v in draw_windows(1, (h, w), 0.5, rng):
            seen[v.top : v.top + v.height, v.left : v.left + v.width] = True
    assert seen.all()


def test_a_windowed_update_is_cheaper_in_pixels_and_still_learns(tiny_model, room, monkeypatch):
    config = AdaptConfig.from_dict({'steps_per_keyframe': 6, 'replay_per_step': 1, 'min_points': 5})
    assert config.photometric_window == 0.5
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match=r'adaptation\.photometric_window'):
            AdaptConfig.from_dict({'photometric_window': bad})
    adapter = Adapter.from_spec(tiny_model, config)
    seen = []

    def recording(log_depth, samples, cfg, windows=None):
        seen.append(None if windows is None else {(v.height, v.width) for v in windows})
        return batch_loss(log_depth, samples, cfg, windows)

    monkeypatch.setattr('depth_fusion_ros.adaptation.adapter.batch_loss', recording)
    reports = [adapter.observe(_sample(room, i)) for i in (1, 2, 3, 4)]
    assert seen and all(s == {(12, 16)} for s in seen)  # 24x32 output, halved
    # Each step's windows differ, so its loss is not comparable with the last step's; the
    # guard's held-out points (the same before and after) say whether the update learned.
    updated = [r for r in reports if r.status == 'updated']
    assert any(r.guard.after < r.guard.before for r in updated if r.guard.keyframes)
