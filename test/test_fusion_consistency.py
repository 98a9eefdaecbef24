"""Stage 3 of the point selection (fusion/consistency.py) against exact ground truth.

A planes-and-boxes scene whose single-view depth is right up to a smooth regional error
except in one region where it is 40 % too near (outside the stage-2 band, as a CNN's badly
predicted segment), and a semi-dense multi-view map with 1 % noise and 15 % wrong matches.
The oracle fuses the estimates within 10 cm of the truth; the paper's two stages lose the
region the network got wrong; stage 3 recovers it and drops the wrong matches.
"""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.fusion.consistency import ConsistencyConfig, consistent_points, local_reference
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import planes_and_boxes

W, H = 160, 120


def _scene(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    depth = planes_and_boxes(W, H, seed=seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    factor = 1.0 + 0.08 * np.sin(xx / 25.0) * np.cos(yy / 30.0)
    wrong_region = xx >= 0.7 * W
    factor[wrong_region] = 0.6
    single = (depth * factor).astype(np.float32)
    estimated = rng.random(depth.shape) < 0.2
    multi = np.where(estimated, depth * (1 + 0.01 * rng.standard_normal(depth.shape)), np.nan)
    wrong = estimated & (rng.random(depth.shape) < 0.15)
    multi[wrong] = depth[wrong] * rng.uniform(0.5, 2.0, size=int(wrong.sum()))
    multi = multi.astype(np.float32)
    stage1 = estimated & (rng.random(depth.shape) < 0.25)
    with np.errstate(invalid='ignore'):
        oracle = estimated & (np.abs(multi - depth) < 0.10)
    return {
        'depth': depth,
        'single': single,
        'multi': multi,
        'stage1': stage1,
        'oracle': oracle,
        'wrong_region': wrong_region,
    }


def _mae(pred: np.ndarray, truth: np.ndarray) -> float:
    return float(np.nanmean(np.abs(pred - truth)))


@pytest.fixture(scope='module')
def fused():
    sc = _scene()
    cfg = FusionConfig(mode='fast')
    off = fuse_keyframe(
        sc['single'], sc['multi'], sc['stage1'], cfg, consistency_config=ConsistencyConfig(enabled=False)
    )
    on = fuse_keyframe(sc['single'], sc['multi'], sc['stage1'], cfg)
    oracle = fuse_keyframe(sc['single'], sc['multi'], None, cfg, omega_mask=sc['oracle'])
    return sc, off, on, oracle


def test_stage3_points_are_right_and_cover_the_badly_predicted_region(fused):
    sc, off, on, _ = fused
    good = sc['oracle']
    precision_off = (off.omega_mask & good).sum() / off.omega_mask.sum()
    precision_on = (on.omega_mask & good).sum() / on.omega_mask.sum()
    assert precision_on >= 0.97 and precision_on > precision_off, (precision_on, precision_off)
    region_good = good & sc['wrong_region']
    assert (off.omega_mask & region_good).sum() < 0.05 * region_good.sum()  # outside the band
    assert (on.omega_mask & region_good).sum() > 0.8 * region_good.sum()
    assert on.evidence['n_added'] > 0 and on.evidence['n_dropped'] >= 0


def test_stage3_closes_most_of_the_gap_to_the_oracle(fused):
    sc, off, on, oracle = fused
    single, e_off, e_on, e_oracle = (
        _mae(x, sc['depth']) for x in (sc['single'], off.depth, on.depth, oracle.depth)
    )
    assert e_oracle < e_off < single
    assert e_off - e_on >= 0.5 * (e_off - e_oracle), (single, e_off, e_on, e_oracle)
    assert on.decision in ('full', 'fewer_points')


def test_local_reference_excludes_the_point_itself():
    import torch

    r = torch.zeros(9, 9)
    r[4, 4] = 1.0  # an outlier among consistent neighbours
    mask = torch.zeros(9, 9, dtype=torch.bool)
    mask[3:6, 3:6] = True
    g = torch.tensor([0.5, 1.0, 0.5])
    mean, support = local_reference(r, mask, g, 1.0)
    assert float(mean[4, 4]) == pytest.approx(0.0, abs=1e-6)
    assert float(support[4, 4]) == pytest.approx(4 * 0.5 + 4 * 0.25, rel=1e-5)  # 8 neighbours


def test_isolated_stage2_points_are_kept_and_isolated_others_are_not():
    s = np.full((40, 40), 2.0, dtype=np.float32)
    m = np.full((40, 40), np.nan, dtype=np.float32)
    m[5, 5] = 2.0  # a lone stage-2 point: nothing to test it against, kept
    m[30, 30] = 3.0  # a lone estimate outside stage 2: never added untested
    omega = np.zeros_like(s, dtype=bool)
    omega[5, 5] = True
    kept, stats = consistent_points(s, m, omega, np.isfinite(m), ConsistencyConfig())
    assert kept[5, 5] and not kept[30, 30] and stats['n_added'] == 0


@pytest.mark.parametrize(
    'field,value',
    [
        ('sigma_px', 0.0),
        ('tolerance', -1.0),
        ('min_support', -0.5),
        ('iterations', 0),
        ('tolerance', float('nan')),
    ],
)
def test_bad_parameters_raise(field, value):
    with pytest.raises(ValueError, match=f'consistency.{field}'):
        ConsistencyConfig(**{field: value})
