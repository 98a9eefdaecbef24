"""The report's fused-against-single errors by distance to the nearest fused point."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.evaluation.distance_bands import band_names, band_sums, band_table


def test_band_sums_split_the_errors_by_distance_to_omega():
    omega = np.zeros((20, 30), dtype=bool)
    omega[10, 10] = True
    gt = np.ones(omega.shape)
    single = np.full(omega.shape, 1.5)
    yy, xx = np.mgrid[:20, :30]
    distance = np.hypot(yy - 10, xx - 10)
    fused = np.where(distance < 2, 1.0, 1.5)  # corrected next to the point only
    single[0, 0] = np.nan  # not scored
    sums = band_sums(single, fused, gt, omega)
    near = (distance < 2).sum()
    assert sums['band0_n'] == near and sums['band0_fused'] == 0.0
    assert sums['band0_single'] == pytest.approx(0.5 * near)
    for i in range(1, len(band_names())):
        assert sums[f'band{i}_fused'] == pytest.approx(sums[f'band{i}_single'])
    assert sum(sums[f'band{i}_n'] for i in range(len(band_names()))) == omega.size - 1
    empty = band_sums(single, fused, gt, np.zeros_like(omega))
    assert empty[f'band{len(band_names()) - 1}_n'] == omega.size - 1 and empty['band0_n'] == 0


def test_band_table_sums_keyframes_per_sequence():
    names = band_names()
    assert names == ['0-2', '2-6', '6-24', '24+']
    per_frame = {f'band{i}_{f}': [0.0, 0.0] for i in range(len(names)) for f in ('n', 'single', 'fused')}
    per_frame['band0_n'] = [10.0, 30.0]
    per_frame['band0_single'] = [4.0, 4.0]
    per_frame['band0_fused'] = [1.0, 1.0]
    per_frame['band3_n'] = [60.0, None]  # a missing value counts as nothing
    per_frame['band3_single'] = [6.0, None]
    per_frame['band3_fused'] = [9.0, None]
    room = {'methods': {'fused': {'per_frame_extras': per_frame}}}
    doc = {'sequences': {'room': room, 'none': {'methods': {}}}}
    table = band_table(doc)
    assert table is not None
    row = next(line for line in table.splitlines() if line.startswith('| room'))
    assert '40%, 0.25' in row and '60%, 1.50' in row and row.count('–') == 2
    assert 'none' not in table
    assert band_table({'sequences': {'x': {'methods': {}}}}) is None
