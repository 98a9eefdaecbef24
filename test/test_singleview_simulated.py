"""The simulated CNN prior: its error statistics follow its parameters; superpixels follow colour."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.singleview.segmentation import slic_superpixels
from depth_fusion_ros.singleview.simulated import (
    SimulatedPrior,
    SimulatedPriorConfig,
    fill_holes,
    simulate_prior,
)

QUIET = dict(
    global_scale_sigma=0.0, deformation_sigma=0.0, noise_sigma=0.0, blur_px=0.0, segment_offset_sigma=0.0
)


def _scene(h: int = 120, w: int = 160, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Colourful blocks (the superpixels' job) over a ramp of depths 1.5-3.5 m."""
    rng = np.random.default_rng(seed)
    rgb = np.zeros((h, w, 3), np.uint8)
    for y in range(0, h, 30):
        for x in range(0, w, 40):
            rgb[y : y + 30, x : x + 40] = rng.integers(0, 256, 3)
    depth = np.tile(np.linspace(1.5, 3.5, w, dtype=np.float32), (h, 1))
    return rgb, depth


def test_superpixels_follow_colour_edges():
    rgb = np.zeros((120, 160, 3), np.uint8)
    rgb[:, :70] = (200, 30, 30)
    rgb[:, 70:] = (30, 30, 200)
    labels = slic_superpixels(rgb, n_segments=12, compactness=10)
    assert labels.shape == (120, 160) and labels.dtype == np.int32
    assert 6 <= labels.max() + 1 <= 20
    left, right = set(np.unique(labels[:, :70])), set(np.unique(labels[:, 70:]))
    assert not left & right  # no segment straddles the colour edge
    with pytest.raises(ValueError, match='uint8'):
        slic_superpixels(rgb.astype(np.float32))


def test_segment_errors_are_one_mode_per_segment():
    """Without noise/deformation the ratio to the truth is constant within each segment and
    equals 1 + e[k]; over many segments e[k] has the configured spread."""
    rgb, gt = _scene()
    cfg = SimulatedPriorConfig(segment_scale_sigma=0.15, n_segments=30, clip_sigmas=0, **QUIET)
    scales = []
    for seed in range(12):
        sim = simulate_prior(gt, rgb, cfg, seed=seed)
        ratio = sim.depth / gt
        for k in np.unique(sim.segments):
            r = ratio[sim.segments == k]
            np.testing.assert_allclose(r, 1 + sim.segment_scale[k], rtol=1e-5)
        scales.append(sim.segment_scale)
    scales = np.concatenate(scales)
    assert abs(np.std(scales) - 0.15) < 0.025 and abs(np.mean(scales)) < 0.03


def test_offsets_global_scale_noise_and_deformation_match_parameters():
    rgb, gt = _scene(240, 320)
    cfg = SimulatedPriorConfig(
        segment_scale_sigma=0.0,
        segment_offset_sigma=0.1,
        global_scale_sigma=0.0,
        deformation_sigma=0.0,
        noise_sigma=0.02,
        blur_px=0.0,
        clip_sigmas=0,
    )
    sim = simulate_prior(gt, rgb, cfg, seed=5)
    residual = sim.depth - gt * (1 + sim.noise) - sim.segment_offset[sim.segments]
    assert np.abs(residual).max() < 1e-5
    assert abs(sim.noise.std() - 0.02) < 0.001 and abs(sim.noise.mean()) < 0.001
    assert 0.05 < np.std(sim.segment_offset) < 0.16
    # the global scale and the smooth deformation
    small_rgb, small_gt = _scene(30, 40)
    cfg_g = SimulatedPriorConfig(global_scale_sigma=0.1, clip_sigmas=0)
    gs = [simulate_prior(small_gt, small_rgb, cfg_g, seed=s).global_scale for s in range(60)]
    assert abs(np.std(gs) - 0.1) < 0.03 and abs(np.mean(gs) - 1) < 0.04
    deform = simulate_prior(gt, rgb, SimulatedPriorConfig(deformation_sigma=0.05), seed=1).deformation
    assert 0.02 < deform.std() < 0.08
    assert np.abs(np.diff(deform, axis=1)).max() < 0.01  # smooth: tiny change between neighbours


def test_errors_are_clipped_and_depth_stays_positive():
    rgb, gt = _scene()
    cfg = SimulatedPriorConfig(segment_scale_sigma=0.3, segment_offset_sigma=1.0, clip_sigmas=2.0)
    sim = simulate_prior(gt, rgb, cfg, seed=2)
    assert np.abs(sim.segment_scale).max() <= 0.6 + 1e-6
    assert np.abs(sim.segment_offset).max() <= 2.0 + 1e-6
    assert sim.depth.min() >= cfg.min_depth


def test_seeded_dense_and_filled():
    rgb, gt = _scene()
    gt_holes = gt.copy()
    gt_holes[40:60, 50:90] = np.nan
    gt_holes[0, :] = 0
    a = simulate_prior(gt_holes, rgb, seed=(0, 7)).depth
    b = simulate_prior(gt_holes, rgb, seed=(0, 7)).depth
    c = simulate_prior(gt_holes, rgb, seed=(0, 8)).depth
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.isfinite(a).all() and a.dtype == np.float32
    filled = fill_holes(gt_holes)
    assert np.isfinite(filled).all() and filled[50, 70] == pytest.approx(gt[50, 70], abs=0.3)
    assert np.array_equal(SimulatedPrior().predict(gt_holes, rgb, seed=(0, 7)), a)


def test_default_error_level_is_like_a_cnn():
    """Defaults aim at 0.2-0.4 m MAE indoors (the paper's Eigen column): relative error ~15-25 %."""
    rgb, gt = _scene(240, 320)
    rel = [np.mean(np.abs(simulate_prior(gt, rgb, seed=s).depth - gt) / gt) for s in range(10)]
    assert 0.1 < np.mean(rel) < 0.3


def test_bad_inputs_and_parameters():
    rgb, gt = _scene()
    with pytest.raises(ValueError, match='no valid pixel'):
        simulate_prior(np.full_like(gt, np.nan), rgb)
    with pytest.raises(ValueError, match='rgb'):
        simulate_prior(gt, rgb[..., 0])
    with pytest.raises(ValueError, match='noise_sigma'):
        SimulatedPriorConfig(noise_sigma=-1).validate()
    with pytest.raises(ValueError, match='unknown'):
        SimulatedPriorConfig.from_dict({'sigma': 1})
