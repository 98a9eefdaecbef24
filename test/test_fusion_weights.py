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
        ({'structure_scale': 0.0}, 'structure_scale'),
        ({'structure_scale': float('nan')}, 'structure_scale'),
    ],
)
def test_bad_parameters_are_named(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        WeightParams(**kwargs)


def _box_on_a_wall(width: int = 96, height: int = 72) -> tuple[np.ndarray, ...]:
    """A box 1.5 m away in front of a wall at 2.5 m; the single view right on the wall and 10 %
    too far on the box; multi-view points all over the box (its texture) and on the wall only
    along the image border, 12 px and more from the box."""
    s = np.full((height, width), 2.5, dtype=np.float32)
    box = np.zeros((height, width), dtype=bool)
    box[24:48, 30:60] = True
    s[box] = 1.65
    m = np.where(box, 1.5, 2.5).astype(np.float32)
    border = np.ones((height, width), dtype=bool)
    border[12:60, 18:72] = False
    omega = (box | border) & (np.indices(s.shape).sum(axis=0) % 3 == 0)
    return s, m, omega, box


@pytest.mark.parametrize('mode', ['exact', 'fast'])
def test_a_finer_structure_scale_keeps_corrections_on_their_surface(mode: str) -> None:
    """The box's correction (-0.15 m) must not bend the wall next to it: with the paper's
    metres (W3, W4 fall to 1/e only a metre off a pixel's plane) the nearby box points
    outweigh the far wall points there; at 0.3 m (the default) the wall's own points win,
    and the box is corrected as well."""
    from depth_fusion_ros.fusion.interpolation import interpolate

    s, m, omega, box = _box_on_a_wall()
    near_wall = np.zeros(box.shape, dtype=bool)  # the wall within 6 px of the box
    near_wall[18:54, 24:66] = True
    near_wall &= ~box
    leak, box_error = {}, {}
    for scale in (1.0, 0.3):
        off = interpolate(s, m, omega, WeightParams(structure_scale=scale), mode=mode).offset
        leak[scale] = float(np.abs(off[near_wall]).mean())
        box_error[scale] = float(np.abs(s[box] + off[box] - 1.5).mean())
    assert leak[0.3] < 0.5 * leak[1.0], leak
    assert box_error[0.3] < min(0.02, box_error[1.0]), box_error


def test_the_structure_scale_is_the_paper_kernel_on_rescaled_depths() -> None:
    """At scale u the interpolation is the paper's on s / u and m / u, its offset times u
    (W1 does not see depth, the offsets are linear in it): exact mode, to float rounding."""
    from depth_fusion_ros.fusion.interpolation import interpolate

    rng = np.random.default_rng(4)
    s = (2.0 + 0.3 * rng.random((40, 50))).astype(np.float32)
    m = (s * (1.0 + 0.1 * rng.standard_normal(s.shape))).astype(np.float32)
    omega = rng.random(s.shape) < 0.05
    u = 0.3
    scaled = interpolate(s, m, omega, WeightParams(structure_scale=u)).offset
    direct = u * interpolate(s / u, m / u, omega, WeightParams()).offset
    np.testing.assert_allclose(scaled, direct, rtol=1e-5, atol=1e-6)
    # arguments are checked as given, before the rescaling (not as the derived threshold)
    with pytest.raises(ValueError, match=r'fast_refine must be in \[0, 1\], got 1.5'):
        interpolate(s, m, omega, WeightParams(structure_scale=u), mode='fast', fast_refine=1.5)
