"""The multi-view depth's bias from an uncertain focal length (``multiview/focal_bias.py``): its
size per estimate, the uncertainty the focal check leaves, and a rotation sweep whose focal
length is 10 % long, which the fusion made worse than its input before the bias was in the std."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.harness import evaluate_sequence
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.focal_bias import (
    MAX_FRAMES,
    MAX_UNCERTAINTY,
    focal_uncertainty,
    inverse_depth_bias,
    spaced,
)

K = np.array([[262.5, 0.0, 159.5], [0.0, 262.5, 119.5], [0.0, 0.0, 1.0]])


def _turned(deg: float, step: float) -> np.ndarray:
    """Keyframe-to-frame transform of a camera turned about y by ``deg`` and moved ``step`` m along x."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('y', deg, degrees=True).as_matrix()
    T[:3, 3] = [step, 0.0, 0.0]
    return T


def _brute_force(u: float, v: float, rho: float, T: np.ndarray, eps: float) -> float:
    """The inverse depth the told camera ``K`` finds along its epipolar line for a point whose
    image in the frame was formed with both focal lengths ``1 + eps`` times as long in the
    rotation's homography (the term ``inverse_depth_bias`` measures), by a dense search."""
    scaled = K.copy()
    scaled[0, 0] *= 1 + eps
    scaled[1, 1] *= 1 + eps
    x = np.array([u, v, 1.0])
    seen = scaled @ T[:3, :3] @ np.linalg.inv(scaled) @ x + rho * (K @ T[:3, 3])
    rhos = np.linspace(0.5 * rho, 2.0 * rho, 300001)
    told = (K @ T[:3, :3] @ np.linalg.inv(K) @ x)[:, None] + rhos[None, :] * (K @ T[:3, 3])[:, None]
    gap = np.hypot(told[0] / told[2] - seen[0] / seen[2], told[1] / told[2] - seen[1] / seen[2])
    return float(rhos[np.argmin(gap)])


def test_the_bias_is_what_a_focal_error_does_to_a_rotating_camera():
    """Turned 2.4 deg while moving 4.8 cm (the rotation stress case's four frames): a focal length
    1 % off moves the estimates by about 2 % of their inverse depth, as a dense search along
    the told line finds; a sideways move without a turn is not biased at all."""
    us, vs = torch.tensor([159.5, 50.0, 300.0]), torch.tensor([119.5, 30.0, 200.0])
    rho = torch.full((3,), 0.4, dtype=torch.float64)
    T = _turned(2.4, 0.048)
    bias = inverse_depth_bias(K, us, vs, rho, [T])
    for i in range(3):
        found = _brute_force(float(us[i]), float(vs[i]), 0.4, T, 0.01)
        assert float(bias[i]) * 0.01 == pytest.approx(abs(found - 0.4), rel=0.05)
    assert 1.0 < float(bias[0] / rho[0]) < 3.0
    sideways = inverse_depth_bias(K, us, vs, rho, [_turned(0.0, 0.048)])
    assert float(sideways.abs().max()) < 1e-9


def test_frames_combine_as_the_filter_weighs_them():
    """Two frames: the one with the longer line (more baseline) counts more, and no frame at all
    leaves no bias; at most ``MAX_FRAMES`` of a long list are taken, evenly, the last one kept."""
    us, vs = torch.tensor([200.0]), torch.tensor([100.0])
    rho = torch.tensor([0.5], dtype=torch.float64)
    near, far = _turned(0.6, 0.012), _turned(2.4, 0.2)
    one, other = (float(inverse_depth_bias(K, us, vs, rho, [T])[0]) for T in (near, far))
    both = float(inverse_depth_bias(K, us, vs, rho, [near, far])[0])
    assert min(one, other) <= both <= max(one, other) and abs(both - other) < abs(both - one)
    assert float(inverse_depth_bias(K, us, vs, rho, [])[0]) == 0.0
    poses = [np.full((4, 4), float(i)) for i in range(30)]
    picked = spaced(poses)
    assert len(picked) == MAX_FRAMES and picked[0] is poses[0] and picked[-1] is poses[-1]
    few = poses[:MAX_FRAMES]
    assert all(a is b for a, b in zip(spaced(few), few, strict=True))


@pytest.mark.parametrize(
    ('verdict', 'scale', 'stderr', 'corrected', 'expected'),
    [
        ('consistent', 1.01, 0.01, False, 0.01),  # verified: the fit's standard error
        ('disagrees', 0.9, 0.01, True, 0.01),  # corrected to the fit
        ('disagrees', 0.9, 0.01, False, -math.log(0.9) + 0.01),  # warn mode: the told one is off
        ('suspect', 1.08, 0.03, False, math.log(1.08) + 0.03),
        ('unobservable', 0.86, 0.181, False, 0.181),  # as unsure as its own fit
        ('unobservable', 0.86, 0.081, False, 0.1),  # never below the prior while unverified
        ('unobservable', 1.0, math.inf, False, MAX_UNCERTAINTY),
        ('unobservable', 1.0, 0.9, False, MAX_UNCERTAINTY),
    ],
)
def test_the_uncertainty_is_what_the_focal_check_verified(verdict, scale, stderr, corrected, expected):
    estimate = SimpleNamespace(verdict=verdict, scale=scale, stderr=stderr, lens_distorted=False)
    assert focal_uncertainty(estimate, 0.1, corrected) == pytest.approx(expected)
    assert focal_uncertainty(None, 0.1, False) == 0.1  # not read yet: the prior
    assert focal_uncertainty(estimate, 0.0, corrected) == 0.0  # 0: off


def test_a_result_that_found_a_lens_verifies_nothing_of_the_distorted_images():
    """The pairs fit a lens distortion better: the images the depth comes from carry the lens's
    error until the lens is taken and the check starts over, so the uncertainty is never below
    the prior, whatever the focal fit's own standard error (a keyframe filtered on the distorted
    images was otherwise trusted at the fit's 2 % and fused at 1.19x its input)."""
    lens = SimpleNamespace(verdict='consistent', scale=1.028, stderr=0.02, lens_distorted=True)
    assert focal_uncertainty(lens, 0.1, False) == 0.1
    assert (
        focal_uncertainty(
            lens, 0.1, False, early=SimpleNamespace(verdict='consistent', scale=1.0, stderr=0.001)
        )
        == 0.1
    )
    wide = SimpleNamespace(verdict='suspect', scale=1.2, stderr=0.05, lens_distorted=True)
    assert focal_uncertainty(wide, 0.1, False) == pytest.approx(math.log(1.2) + 0.05)  # larger: kept
    assert focal_uncertainty(lens, 0.0, False) == 0.0  # 0: off
    plain = SimpleNamespace(verdict='consistent', scale=1.028, stderr=0.02, lens_distorted=False)
    assert focal_uncertainty(plain, 0.1, False) == pytest.approx(0.02)  # no lens: verified


def test_an_early_agreement_bounds_the_uncertainty_until_the_result():
    """Before the result, an early look that agreed bounds the focal error by its offset and
    two standard errors where that is below the prior; one that did not agree says nothing,
    and the result, once there, decides alone."""
    early = SimpleNamespace(verdict='consistent', scale=1.01, stderr=0.01)
    assert focal_uncertainty(None, 0.1, False, early) == pytest.approx(math.log(1.01) + 0.02)
    wide = SimpleNamespace(verdict='consistent', scale=1.04, stderr=0.04)
    assert focal_uncertainty(None, 0.1, False, wide) == 0.1  # never above the prior
    unsure = SimpleNamespace(verdict='unobservable', scale=1.0, stderr=0.001)
    assert focal_uncertainty(None, 0.1, False, unsure) == 0.1
    final = SimpleNamespace(verdict='unobservable', scale=0.86, stderr=0.181, lens_distorted=False)
    assert focal_uncertainty(final, 0.1, False, early) == pytest.approx(0.181)
    assert focal_uncertainty(None, 0.0, False, early) == 0.0  # 0: off


def test_the_filter_publishes_the_bias_in_the_std_only():
    """The same stream with and without the focal uncertainty: the same estimates, depths and
    posterior; only ``depth_std`` grows, by more where the rotation dominates."""
    sequence = render_sequence(stress_config('rotation', width=160, height=120, frames=12, seed=0))
    results = []
    for uncertainty in (0.0, 0.1):
        filt = DepthFilter(sequence.camera, FilterConfig(focal_uncertainty=uncertainty))
        for frame in sequence.frames:
            filt.process(frame.gray, frame.pose)
        assert filt.key is not None and filt.key.update_poses
        results.append(filt.result(sequence.frames[-1].pose))
    off, on = results
    has = np.isfinite(off.depth)
    assert has.sum() > 100
    np.testing.assert_array_equal(on.depth, off.depth)
    np.testing.assert_array_equal(on.variance, off.variance)
    grown = on.depth_std[has] / off.depth_std[has]
    assert np.all(grown >= 1.0) and np.median(grown) > 1.5
    # The bias is published apart as well (the guard weighs the points' scale by it): the std
    # is the posterior's and the bias's in quadrature, and without an uncertainty it is 0.
    np.testing.assert_array_equal(np.isfinite(on.bias_std), has)
    quadrature = off.depth_std[has] ** 2 + on.bias_std[has] ** 2
    np.testing.assert_allclose(on.depth_std[has] ** 2, quadrature, rtol=1e-4)
    assert np.all(off.bias_std[has] == 0.0) and np.median(on.bias_std[has] / on.depth[has]) > 0.01


def _ratio(sequence, uncertainty: float) -> float:
    """Fused / single-view MAE of frame 15, read causally as the node reads the stream."""
    options = EvalOptions(
        frames=len(sequence),
        keyframes=[15],
        single_view='simulated',
        width=320,
        height=240,
        neighbour_mode='online',
        params={
            'fusion': {'compile_kernel': False, 'mode': 'fast', 'max_points': 4096},
            'filter': {'focal_uncertainty': uncertainty},
        },
    )
    result = evaluate_sequence(sequence, ['single_view_simulated', 'fused'], options, show_progress=False)
    assert result.focal_check is None  # 20 frames: the check has not read enough to verify it
    return (
        result.records['fused'].all.summary()['mae']
        / result.records['single_view_simulated'].all.summary()['mae']
    )


@pytest.mark.parametrize('seed', [0, 2])
def test_a_rotation_sweep_with_a_focal_length_10_percent_long_is_never_worse(seed):
    """The rotation stress case told a focal length 10 % long, before the focal check can read
    it: every multi-view depth is biased the same way (twice the error of the case with the
    right focal length) and agrees with its neighbours; fused on trust it was 1.05-1.08x the
    single-view MAE. With the bias of an unverified focal length in the std (the default
    ``filter.focal_uncertainty``), the guard sees that the points cannot say more than the
    single view, and the depth is no worse than its input."""
    sequence = render_sequence(
        stress_config('rotation', width=320, height=240, frames=20, seed=seed, focal_error=0.1)
    )
    assert _ratio(sequence, 0.0) > 1.0
    assert _ratio(sequence, FilterConfig().focal_uncertainty) <= 1.0
