"""Metrics against hand-computed values."""

import numpy as np

from depth_fusion_ros.metrics import MetricAccumulator, frame_metrics, high_gradient_mask, upsample_depth


def test_metrics_known_values():
    gt = np.array([[1.0, 2.0], [4.0, np.nan]])
    pred = np.array([[1.5, 2.0], [2.0, 3.0]])
    m = frame_metrics(pred, gt)
    assert m['n_pixels'] == 3
    assert np.isclose(m['mae'], (0.5 + 0 + 2) / 3)
    assert np.isclose(m['rmse'], np.sqrt((0.25 + 4) / 3))
    assert np.isclose(m['abs_rel'], (0.5 + 0 + 0.5) / 3)
    assert np.isclose(m['delta1'], 1 / 3)  # only 2 vs 2 is within 1.25
    d = np.log([1, 2, 4]) - np.log([1.5, 2, 2])
    assert np.isclose(m['si'], np.mean(d**2) - np.mean(d) ** 2)


def test_perfect_and_scaled_predictions():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.5, 5, size=(48, 64))
    assert frame_metrics(gt, gt)['mae'] == 0
    m = frame_metrics(2 * gt, gt)
    assert np.isclose(m['si'], 0, atol=1e-12) and np.isclose(m['abs_rel'], 1)


def test_sparse_predictions_and_pooling():
    gt = np.ones((4, 4))
    pred = np.full((4, 4), np.nan)
    pred[0, 0] = 2
    acc = MetricAccumulator()
    acc.add(pred, gt)
    acc.add(np.full((4, 4), np.nan), gt)
    s = acc.summary()
    assert s['n_pixels'] == 1 and s['mae'] == 1
    assert np.isnan(acc.mae_per_frame[1])


def test_upsampling_keeps_holes_and_interpolates_dense():
    dense = np.arange(4, dtype=np.float32).reshape(2, 2)
    assert upsample_depth(dense, 4, 4).shape == (4, 4)
    holes = dense.copy()
    holes[0, 0] = np.nan
    up = upsample_depth(holes, 4, 4)
    assert np.isnan(up[:2, :2]).all() and np.isfinite(up[2:, 2:]).all()


def test_gradient_split():
    gray = np.zeros((32, 32), np.float32)
    gray[:, 16:] = 1
    mask = high_gradient_mask(gray)
    assert mask[:, 15:17].all() and not mask[:, :10].any()
