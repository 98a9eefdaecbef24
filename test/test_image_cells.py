"""Square image cells shared by the filter's per-region minority test and the adaptation's coverage."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros.image_cells import ImageCells


def test_eight_across_is_eight_by_six_at_four_to_three_and_numpy_and_torch_agree():
    cells = ImageCells.across(320, 240, 8)
    assert (cells.side, cells.columns, cells.rows, cells.count) == (40, 8, 6, 48)
    wide = ImageCells.across(640, 360, 8)
    assert (wide.side, wide.columns, wide.rows) == (80, 8, 5)  # the last row is partial
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-5, 330, 500), rng.uniform(-5, 250, 500)
    index = cells.index(u, v)
    assert index.min() >= 0 and index.max() < cells.count  # outside positions clamp to the border
    assert cells.index(np.array([39.9, 40.0]), np.array([0.0, 239.0])).tolist() == [0, 41]
    np.testing.assert_array_equal(cells.index(torch.from_numpy(u), torch.from_numpy(v)).numpy(), index)
    with pytest.raises(ValueError, match='cells across'):
        ImageCells.across(320, 240, 0)
