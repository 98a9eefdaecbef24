"""The certainty floor of the interpolation (``fusion.certainty_floor``): every correction
times ``ΣW̃ / (ΣW̃ + κ)``, exact and fast, whatever share of Ω ``max_points`` keeps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from depth_fusion_ros.fusion.guard import GuardVerdict
from depth_fusion_ros.fusion.interpolation import MAX_CERTAINTY_FLOOR, interpolate
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe, keyframe_floor
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
    """The configured floor is in [0, 1]; the one a keyframe's evidence raised it to (what
    ``interpolate`` is given) at most ``MAX_CERTAINTY_FLOOR``."""
    with pytest.raises(ValueError, match='certainty_floor'):
        FusionConfig(certainty_floor=value)
    s = np.ones((10, 10), np.float32)
    with pytest.raises(ValueError, match='certainty_floor'):
        interpolate(s, s, s > 0, certainty_floor=value if value != 1.5 else MAX_CERTAINTY_FLOOR + 1)


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


def _verdict(mv_noise: float, single_error: float, scale: float = 1.0) -> GuardVerdict:
    evidence = {'mv_noise': mv_noise, 'single_error': single_error}
    return GuardVerdict('full', 'test', np.zeros((2, 2), bool), 1.0, scale, evidence)


def test_the_floor_follows_the_single_views_precision_against_the_points() -> None:
    """``certainty_gain``: κ is at least gain × (mv_noise / single_error)², the single-view
    depth's precision relative to a point's, as the guard measured them; never below
    ``certainty_floor``, never above ``MAX_CERTAINTY_FLOOR``, the fixed floor where the
    guard measured nothing (off, or too few points)."""
    config = FusionConfig(certainty_floor=0.1, certainty_gain=30.0)
    # A network 10x the points' noise (the paper's regime): the floor as configured.
    assert keyframe_floor(config, _verdict(0.02, 0.2)) == pytest.approx(0.3)
    assert keyframe_floor(dataclasses.replace(config, certainty_gain=5.0), _verdict(0.02, 0.2)) == 0.1
    # One 2.5x the points' noise (adapted to the scene, or a good metric model): 4.8.
    assert keyframe_floor(config, _verdict(0.02, 0.05)) == pytest.approx(4.8)
    # As precise as the points, or the fit spread all noise: the cap.
    assert keyframe_floor(config, _verdict(0.02, 0.01)) == MAX_CERTAINTY_FLOOR
    assert keyframe_floor(config, _verdict(0.02, 0.0)) == MAX_CERTAINTY_FLOOR
    assert keyframe_floor(config, None) == 0.1
    assert keyframe_floor(config, _verdict(float('nan'), 0.1)) == 0.1
    assert keyframe_floor(dataclasses.replace(config, certainty_gain=0.0), _verdict(0.02, 0.01)) == 0.1


@pytest.mark.parametrize('value', [-1.0, float('inf'), float('nan')])
def test_a_bad_gain_is_named(value: float) -> None:
    with pytest.raises(ValueError, match='certainty_gain'):
        FusionConfig(certainty_gain=value)


def test_the_keyframes_floor_is_reported_and_fades_a_precise_priors_corrections() -> None:
    """The floor a keyframe used is in its evidence (``certainty_floor``); a single-view depth
    that the points barely correct (its error about their noise) keeps more of itself."""
    sc = make_scene(80, 60, n_points=300, scale=1.0, offset=0.0)
    rng = np.random.default_rng(0)
    multi = sc.multi * np.exp(rng.normal(0.0, 0.02, sc.multi.shape)).astype(np.float32)
    single = sc.single * np.exp(rng.normal(0.0, 0.03, sc.single.shape)).astype(np.float32)
    plain = fuse_keyframe(single, multi, None, FusionConfig(certainty_gain=0.0), 'metric_depth')
    raised = fuse_keyframe(single, multi, None, FusionConfig(certainty_gain=30.0), 'metric_depth')
    assert plain.evidence['certainty_floor'] == FusionConfig().certainty_floor
    assert raised.evidence['certainty_floor'] > 1.0
    assert raised.evidence['certainty'] < plain.evidence['certainty']


def test_a_single_view_off_by_one_global_factor_keeps_the_fixed_floor() -> None:
    """The single-view error counts its global scale against the points: a network precise
    about the fit but off by a factor of two everywhere (the shipped one on TUM fr1_xyz) is
    far off, and its corrections must reach the whole image."""
    config = FusionConfig(certainty_floor=0.1, certainty_gain=30.0)
    off = _verdict(0.02, 0.02, scale=2.0)
    assert keyframe_floor(config, off) == pytest.approx(
        max(0.1, 30.0 * (0.02 / np.hypot(0.02, np.log(2.0))) ** 2)
    )
    assert keyframe_floor(config, off) < 0.1 + 1e-9
