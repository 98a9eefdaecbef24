"""Undoing a radial lens distortion by Newton's method on the radius (``radial_lens.py``)."""

from __future__ import annotations

import numpy as np

from depth_fusion_ros.multiview.lens_fit import K1_GRID
from depth_fusion_ros.radial_lens import undistort_radial


def test_the_lens_checks_grid_is_undone_exactly_and_a_fold_is_kept():
    """Every candidate of the focal check's lens grid against points over a 320x240 image (and
    past its corners): where the distortion has an inverse, distorting the result again gives
    the points back to 1e-12; past a barrel distortion's fold, where it has none, the radius is
    the fold's, finite."""
    rng = np.random.default_rng(7)
    xd = rng.uniform(-160, 160, 400) / 262.5 * 1.3
    yd = rng.uniform(-120, 120, 400) / 262.5 * 1.3
    k1 = K1_GRID[:, None]
    x, y = undistort_radial(xd, yd, k1)
    assert x.shape == y.shape == (len(K1_GRID), 400) and np.isfinite(x).all() and np.isfinite(y).all()
    r = np.hypot(x, y)
    fold = np.sqrt(-1.0 / (3.0 * np.minimum(k1, -1e-300)))
    has_root = np.hypot(xd, yd) < fold * 2.0 / 3.0
    again = np.stack([x * (1 + k1 * r * r) - xd, y * (1 + k1 * r * r) - yd])
    assert np.abs(again[:, has_root]).max() < 1e-12
    assert (~has_root).any() and np.allclose(r[~has_root], np.broadcast_to(fold, r.shape)[~has_root])
    assert np.array_equal(undistort_radial(xd, yd, 0.0)[0], xd)  # no distortion: as they are
