"""Weights W1..W4 and their normalisation (paper §III-C) against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from depth_fusion_ros.fusion.weights import (
    Samples,
    WeightParams,
    depth_gradients,
    normalise_weights,
    unnormalised_weights,
)


def _sample(x: float, y: float, s: float, gx: float, gy: float) -> Samples:
    return Samples(*(torch.tensor([v], dtype=torch.float32) for v in (x, y, s, gx, gy)))


def test_factors_match_the_paper_formulas() -> None:
    p = _sample(10, 20, 2.0, 0.01, -0.02)
    q = _sample(13, 24, 2.1, 0.03, 0.00)
    params = WeightParams(sigma1=15, sigma2=0.1, sigma3=1e-3, weights='all')
    w1 = math.exp(-5.0 / 15)
    w2 = 1 / ((0.02 + 0.1) * (0.02 + 0.1))
    w3 = math.exp(-abs(2.0 + 0.01 * 3 - 2.1)) + 1e-3
    w4 = math.exp(-abs(2.0 - 0.02 * 4 - 2.1)) + 1e-3
    got = unnormalised_weights(p.column(), q.row(), params).item()
    assert got == pytest.approx(w1 * w2 * w3 * w4, rel=1e-5)
    got_w1 = unnormalised_weights(p.column(), q.row(), WeightParams(weights='w1')).item()
    assert got_w1 == pytest.approx(w1, rel=1e-6)
    got_w12 = unnormalised_weights(p.column(), q.row(), WeightParams(weights='w1w2')).item()
    assert got_w12 == pytest.approx(w1 * w2, rel=1e-5)


def test_normalised_weights_sum_to_one_and_drop_the_minimum() -> None:
    w = torch.rand(50, 7, generator=torch.Generator().manual_seed(0)) + 0.1
    n = normalise_weights(w)
    assert torch.allclose(n.sum(dim=1), torch.ones(50), atol=1e-6)
    assert torch.all(n >= 0)
    # The smallest weight of every row becomes exactly 0 (min subtraction).
    assert torch.all(n.gather(1, w.argmin(dim=1, keepdim=True)) == 0)


def test_normalisation_guards_single_point_and_equal_weights() -> None:
    assert torch.equal(normalise_weights(torch.tensor([[0.3], [0.0]])), torch.tensor([[1.0], [1.0]]))
    equal = normalise_weights(torch.full((2, 4), 0.25))
    assert torch.allclose(equal, torch.full((2, 4), 0.25))
    assert torch.allclose(normalise_weights(torch.zeros(1, 4)), torch.full((1, 4), 0.25))
    assert normalise_weights(torch.zeros(3, 0)).shape == (3, 0)


def test_weights_stay_positive_and_normal_far_away() -> None:
    """Huge distances and depth mismatches never underflow to 0 or into denormals."""
    p = _sample(0, 0, 1.0, 0.0, 0.0)
    q = _sample(5000, 5000, 400.0, 3.0, -3.0)
    w = unnormalised_weights(p.column(), q.row(), WeightParams()).item()
    assert w > 0 and w >= torch.finfo(torch.float32).tiny


def test_depth_gradients_are_metres_per_pixel_and_hole_safe() -> None:
    yy, xx = np.mgrid[0:6, 0:8].astype(np.float32)
    s = 2.0 + 0.05 * xx - 0.02 * yy
    gx, gy = depth_gradients(s)
    assert np.allclose(gx, 0.05, atol=1e-6) and np.allclose(gy, -0.02, atol=1e-6)
    s[2, 3] = np.nan
    gx, gy = depth_gradients(s)
    assert np.all(np.isfinite(gx)) and np.all(np.isfinite(gy))


@pytest.mark.parametrize(
    ('kwargs', 'name'),
    [
        ({'sigma1': 0}, 'sigma1'),
        ({'sigma2': -1}, 'sigma2'),
        ({'sigma3': -1}, 'sigma3'),
        ({'weights': 'w3'}, 'weights'),
    ],
)
def test_bad_parameters_are_named(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        WeightParams(**kwargs)
