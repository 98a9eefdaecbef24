"""The certainty floor of the interpolation (``fusion.certainty_floor``): every correction
times ``ΣW̃ / (ΣW̃ + κ)``, exact and fast, whatever share of Ω ``max_points`` keeps."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.fusion.weights import (
    WeightParams,
    depth_gradients,
    normalise_weights,
    samples_at,
    unnormalised_weights,
)


def _reference(s: np.ndarray, m: np.ndarray, omega: np.ndarray, floor: float) -> np.ndarray:
    """Offsets straight from the formulas: the paper's normalised sum (eq. (9), the minimum
    subtracted) times ``mass / (mass + κ)``, the mass the plain sum of the weights."""
    params = WeightParams()
    gx, gy = (torch.from_numpy(g.ravel()) for g in depth_gradients(s))
    st = torch.from_numpy(s.ravel())
    pixels = samples_at(torch.arange(s.size), s.shape[1], st, gx, gy).column()
    q = torch.from_numpy(np.flatnonzero(omega))
    points = samples_at(q, s.shape[1], st, gx, gy).row()
    w = unnormalised_weights(pixels, points, params).double()
    v = torch.from_numpy((m - s).ravel()[q.numpy()]).double()
    mass = w.sum(dim=1)
    kappa = floor * params.max_weight
    return ((normalise_weights(w) @ v) * mass / (mass + kappa)).reshape(s.shape).numpy()


@pytest.mark.parametrize('floor', [0.0, 0.05, 1.0])
def test_the_fade_is_the_formula_in_every_chunking(floor: float) -> None:
    sc = make_scene(40, 30, n_points=25)
    omega = np.isfinite(sc.multi)
    reference = _reference(sc.single, sc.multi, omega, floor)
    for chunk in (7, 1 << 20):
        got = interpolate(sc.single, sc.multi, omega, chunk_elements=chunk, certainty_floor=floor).offset
        assert np.allclose(got, reference, atol=2e-5)
    if floor == 0:
        assert np.array_equal(reference, _reference(sc.single, sc.multi, omega, 0.0))
        paper = interpolate(sc.single, sc.multi, omega).offset
        assert np.array_equal(interpolate(sc.single, sc.multi, omega, certainty_floor=0.0).offset, paper)


def test_a_correction_fades_where_no_point_resembles_the_pixel() -> None:
    """Four points in one corner of a flat wall: the correction stays nearly whole at the
    points and fades with the distance, in the exact and the fast mode alike."""
    s = np.full((60, 80), 2.0, np.float32)
    m = np.full_like(s, np.nan)
    m[11:13, 11:13] = 2.4
    omega = np.isfinite(m)
    for mode in ('exact', 'fast'):
        paper = interpolate(s, m, omega, mode=mode).offset
        faded = interpolate(s, m, omega, mode=mode, certainty_floor=0.1).offset
        assert np.allclose(paper, 0.4, atol=1e-5)  # normalised: the full correction everywhere
        assert faded[12, 12] == pytest.approx(0.4, rel=0.03)
        profile = faded[12, 12::8]
        assert np.all(np.diff(profile) < 0) and profile[-1] < 0.15
        assert faded[55, 75] < 0.08


def test_fast_mode_follows_the_exact_fade() -> None:
    sc = make_scene(80, 60, n_points=60)
    omega = np.isfinite(sc.multi)
    exact = interpolate(sc.single, sc.multi, omega, certainty_floor=0.1).offset
    fast = interpolate(sc.single, sc.multi, omega, mode='fast', certainty_floor=0.1).offset
    assert np.abs(fast - exact).mean() < 0.05 * np.abs(exact).mean()


def test_a_subsample_of_omega_fades_like_the_whole() -> None:
    """``max_points`` keeps a share of Ω and so of its weight; the floor follows, so the
    fade is about the same with 1/4 of the points as with all of them."""
    sc = make_scene(80, 60, n_points=100, scale=1.0, offset=0.3)
    base = dict(guard=False, certainty_floor=1.0)
    whole = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(**base), 'metric_depth')
    capped = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(**base, max_points=25), 'metric_depth')
    paper = fuse_keyframe(
        sc.single, sc.multi, None, FusionConfig(guard=False, certainty_floor=0.0), 'metric_depth'
    )
    kept = np.nanmean(sc.single - whole.depth)  # the correction is 0.3 m everywhere
    assert 0.1 < kept < 0.27  # the floor is felt
    assert np.nanmean(sc.single - capped.depth) == pytest.approx(kept, rel=0.05)
    assert np.nanmean(sc.single - paper.depth) == pytest.approx(0.3, abs=0.01)


@pytest.mark.parametrize('value', [-0.1, 1.5, float('nan')])
def test_a_bad_floor_is_named(value: float) -> None:
    with pytest.raises(ValueError, match='certainty_floor'):
        FusionConfig(certainty_floor=value)
    s = np.ones((10, 10), np.float32)
    with pytest.raises(ValueError, match='certainty_floor'):
        interpolate(s, s, s > 0, certainty_floor=value)


def test_the_share_kept_is_reported_per_keyframe() -> None:
    """``Interpolation.kept``: the mean share of the correction kept (1 without a floor; the
    fast mode's is its coarse grid's), and ``FusionResult.evidence['certainty']`` carries it
    with the guard on or off (the node's decision JSON and the report's extras read it)."""
    s = np.full((60, 80), 2.0, np.float32)
    m = np.full_like(s, np.nan)
    m[11:13, 11:13] = 2.4
    omega = np.isfinite(m)
    assert interpolate(s, m, omega).kept == 1.0
    exact = interpolate(s, m, omega, certainty_floor=0.1)
    assert exact.kept == pytest.approx(float(np.mean(exact.offset / 0.4)), rel=1e-4)
    assert 0.1 < exact.kept < 0.9
    assert interpolate(s, m, omega, mode='fast', certainty_floor=0.1).kept == pytest.approx(
        exact.kept, abs=0.03
    )
    sc = make_scene(80, 60, n_points=100, scale=1.0, offset=0.3)
    for guard in (True, False):
        result = fuse_keyframe(sc.single, sc.multi, None, FusionConfig(guard=guard), 'metric_depth')
        assert 0.0 < result.evidence['certainty'] < 1.0
