"""Stage-2 selection: RANSAC m ≈ a·s + b rejects planted outliers, degenerate inputs fall back."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.fusion.selection import fit_least_squares, fit_ransac


def _line_with_outliers(n: int = 300, n_out: int = 60, seed: int = 0):
    rng = np.random.default_rng(seed)
    s = rng.uniform(0.5, 3.0, n)
    m = 1.3 * s + 0.2 + rng.normal(0, 0.01, n)
    out = rng.choice(n, n_out, replace=False)
    up = rng.random(n_out) < 0.5
    m[out] = np.where(up, m[out] + rng.uniform(0.6, 2.0, n_out), m[out] * rng.uniform(0.3, 0.6, n_out))
    truth = np.ones(n, dtype=bool)
    truth[out] = False
    return s, m, truth


@pytest.mark.parametrize('relative', [False, True])
def test_ransac_rejects_planted_outliers(relative: bool) -> None:
    s, m, truth = _line_with_outliers()
    fit = fit_ransac(s, m, threshold=0.08 if relative else 0.1, relative=relative, seed=3)
    assert fit.ok and fit.reason is None
    assert fit.a == pytest.approx(1.3, abs=0.02) and fit.b == pytest.approx(0.2, abs=0.04)
    assert np.array_equal(fit.inliers, truth)


def test_ransac_is_deterministic_for_a_seed() -> None:
    s, m, _ = _line_with_outliers(n_out=120)
    a = fit_ransac(s, m, seed=7, iterations=20)
    b = fit_ransac(s, m, seed=7, iterations=20)
    assert (a.a, a.b) == (b.a, b.b) and np.array_equal(a.inliers, b.inliers)


def test_many_points_are_scored_on_a_subsample_and_every_point_is_judged(monkeypatch) -> None:
    """Beyond SCORE_POINTS the hypotheses are ranked on a seeded subsample (the filter's
    20-40k points): the same line as ranking on every point, inliers over all of them."""
    from depth_fusion_ros.fusion import selection

    s, m, truth = _line_with_outliers(n=30_000, n_out=9_000, seed=4)
    fit = fit_ransac(s, m, threshold=0.1, seed=3)
    again = fit_ransac(s, m, threshold=0.1, seed=3)
    assert (fit.a, fit.b) == (again.a, again.b) and np.array_equal(fit.inliers, again.inliers)
    monkeypatch.setattr(selection, 'SCORE_POINTS', 10**9)  # every point scored: the old way
    full = fit_ransac(s, m, threshold=0.1, seed=3)
    assert fit.a == pytest.approx(full.a, rel=1e-3) and fit.b == pytest.approx(full.b, abs=1e-3)
    assert fit.inliers.size == 30_000 and (fit.inliers != full.inliers).sum() <= 30
    assert (fit.inliers & ~truth).sum() <= 0.01 * truth.sum()


def test_inverse_depth_model() -> None:
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.8, 4.0, 200)
    s = 3.0 / depth - 0.1  # a relative inverse depth (scale 3, shift -0.1)
    fit = fit_ransac(s, depth, inverse=True, threshold=0.02, relative=False)
    assert fit.ok
    assert np.allclose(fit.predict(s), depth, rtol=1e-4)


@pytest.mark.parametrize('seed', range(12))
def test_inverse_fit_survives_hypotheses_that_put_points_at_infinity(seed: int) -> None:
    """Random two-point lines through outliers predict a non-positive inverse depth (a depth
    at infinity) for some points. Those points are outliers of that line; their residual
    (inf / inf) once made the whole hypothesis' cost NaN, ``argmin`` then returned that NaN
    row and RANSAC kept whatever line came last: 11 of 30 such fits failed before the fix."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0.2, 1.0, 3000)  # a disparity-like output: 1 / depth = 2 s + 0.1
    depth = 1.0 / (2.0 * s + 0.1)
    bad = rng.random(s.size) < 0.6
    depth[bad] = rng.uniform(0.3, 5.0, int(bad.sum()))
    fit = fit_ransac(s, depth, threshold=0.1, relative=True, inverse=True, seed=seed)
    assert fit.ok and fit.a == pytest.approx(2.0, rel=0.02) and fit.b == pytest.approx(0.1, abs=0.01)
    assert fit.inliers[~bad].mean() > 0.99


def test_degenerate_inputs_fail_with_a_reason() -> None:
    assert fit_ransac(np.array([1.0]), np.array([1.0]), min_inliers=2).reason == 'too_few_points'
    assert fit_ransac(np.ones(5), np.arange(5.0) + 1, min_inliers=10).reason == 'too_few_points'
    # Every single-view value equal: no line through two distinct points exists.
    assert fit_ransac(np.ones(50), np.linspace(1, 3, 50)).reason == 'no_consensus'
    # Pure noise: nothing gathers min_inliers within 1 cm.
    rng = np.random.default_rng(0)
    noisy = fit_ransac(
        rng.uniform(1, 3, 40), rng.uniform(1, 9, 40), threshold=0.01, relative=False, min_inliers=20
    )
    assert not noisy.ok and noisy.reason == 'no_consensus'
    assert fit_least_squares(np.array([2.0]), np.array([1.0])).reason == 'too_few_points'


@pytest.mark.parametrize(
    ('kwargs', 'name'),
    [
        ({'threshold': 0}, 'ransac_threshold'),
        ({'iterations': 0}, 'ransac_iterations'),
        ({'min_inliers': 1}, 'ransac_min_inliers'),
    ],
)
def test_bad_ransac_parameters_are_named(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        fit_ransac(np.arange(10.0), np.arange(10.0), **kwargs)


def test_scale_model_and_plausible_scales_resist_a_clustered_majority_of_outliers() -> None:
    """Wrong matches piling up at the near end of the sweep (m ≈ 0.25 m) outnumber the good
    points; an unconstrained line follows them, a plausible metric scale does not."""
    rng = np.random.default_rng(2)
    s = rng.uniform(2.0, 4.0, 400)
    m = 1.1 * s * (1 + rng.normal(0, 0.02, 400))
    wrong = np.arange(400) < 240
    m[wrong] = rng.uniform(0.24, 0.26, wrong.sum())
    free = fit_ransac(s, m, threshold=0.2, relative=True)
    assert free.inliers[wrong].mean() > 0.9  # the line found the cluster
    fit = fit_ransac(s, m, threshold=0.2, relative=True, affine=False, scale_range=(0.5, 2.0))
    assert fit.ok and fit.b == 0.0 and fit.a == pytest.approx(1.1, abs=0.02)
    assert np.array_equal(fit.inliers, ~wrong)
