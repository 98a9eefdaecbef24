"""Points in a silhouette's halo (fusion/occlusion.py) on a scene with exact ground truth.

A box 1.5 m away in front of a wall 3 m away, both flat grey (the box brighter): the only
texture at the box is its silhouette. A patch matcher gives the two background columns next to
it the box's depth (foreground fattening); the test builds that multi-view map by hand: the
box's depth on both sides of its silhouette, 2 px deep each. The wall has textured stripes far
from the box (correct points), and a floor below it a textured ramp (correct points on a
slanted surface). The single view is the truth 5 % too far, blurred (a network's soft edges).
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from depth_fusion_ros.fusion.occlusion import halo_points
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe

W, H = 160, 120
BOX = (50, 110, 30, 80)  # x0, x1, y0, y1 (exclusive ends)
FLOOR_Y = 95


def _scene() -> dict[str, np.ndarray]:
    yy, xx = np.mgrid[0:H, 0:W]
    x0, x1, y0, y1 = BOX
    box = (xx >= x0) & (xx < x1) & (yy >= y0) & (yy < y1)
    depth = np.full((H, W), 3.0, dtype=np.float32)
    floor = yy >= FLOOR_Y
    depth[floor] = 3.0 - 0.04 * (yy[floor] - FLOOR_Y)
    depth[box] = 1.5
    image = np.full((H, W), 0.3, dtype=np.float32)
    image[box] = 0.8
    stripes = (xx < 30) & (yy < FLOOR_Y) & ((xx // 4) % 2 == 0)
    image[stripes] = 0.5
    floor_stripes = (yy >= 108) & ((yy // 4) % 2 == 0) & (xx > 20) & (xx < 140)
    image[floor_stripes] = 0.55
    single = np.exp(gaussian_filter(np.log(depth * 1.05), 1.5)).astype(np.float32)
    # The silhouette's two rings: 2 px outside (the halo) and 2 px inside, away from the corners.
    inner = box & ~((xx >= x0 + 2) & (xx < x1 - 2) & (yy >= y0 + 2) & (yy < y1 - 2))
    grown = (xx >= x0 - 2) & (xx < x1 + 2) & (yy >= y0 - 2) & (yy < y1 + 2)
    halo = grown & ~box
    off_corner = ((xx >= x0 + 4) & (xx < x1 - 4)) | ((yy >= y0 + 4) & (yy < y1 - 4))
    halo &= off_corner
    inner &= off_corner
    stripe_edges = (xx < 28) & (xx > 2) & (yy < FLOOR_Y - 8) & (yy > 4) & (xx % 4 <= 1)
    floor_edges = (yy >= 110) & (yy < 117) & (yy % 4 <= 1) & (xx > 24) & (xx < 136)
    m = np.full((H, W), np.nan, dtype=np.float32)
    m[halo | inner] = 1.5
    m[stripe_edges | floor_edges] = depth[stripe_edges | floor_edges]
    return {
        'depth': depth,
        'image': image,
        'single': single,
        'm': m,
        'halo': halo,
        'inner': inner,
        'correct': stripe_edges | floor_edges,
        'floor': floor_edges,
    }


def test_the_halo_is_found_and_nothing_else() -> None:
    sc = _scene()
    points = np.isfinite(sc['m'])
    found = halo_points(sc['image'], sc['single'], sc['m'], points)
    assert found.sum() >= 0.9 * sc['halo'].sum()
    assert not (found & sc['inner']).any(), 'the foreground side of the silhouette is right'
    assert not (found & sc['correct']).any(), 'points off any occluding edge stay (the ramp too)'


def test_a_single_view_without_the_step_keeps_every_point() -> None:
    sc = _scene()
    flat = np.full((H, W), 2.5, dtype=np.float32)
    points = np.isfinite(sc['m'])
    assert not halo_points(sc['image'], flat, sc['m'], points).any()
    assert not halo_points(sc['image'], sc['single'], sc['m'], points, min_step=0.0).any()


def test_an_rgb_image_is_read_as_its_grey_and_a_wrong_size_is_an_error() -> None:
    sc = _scene()
    points = np.isfinite(sc['m'])
    rgb = np.repeat((sc['image'] * 255).astype(np.uint8)[..., None], 3, axis=2)
    grey = halo_points(sc['image'], sc['single'], sc['m'], points)
    assert np.array_equal(halo_points(rgb, sc['single'], sc['m'], points), grey)
    with pytest.raises(ValueError, match='keyframe image'):
        halo_points(sc['image'][:-1], sc['single'], sc['m'], points)


def test_the_fusion_without_the_halo_is_nearer_the_truth() -> None:
    sc = _scene()
    # The edge cut off (edge_points.py): this scene's points concentrate on the box's edges, and
    # the cut would zero the halo's corrections first (test_fusion_edge_points.py).
    config = FusionConfig(edge_ratio=0.0)
    without = fuse_keyframe(sc['single'], sc['m'], None, config)
    with_image = fuse_keyframe(sc['single'], sc['m'], None, config, image=sc['image'])
    assert without.evidence['halo_checked'] == 0.0
    assert with_image.evidence['halo_checked'] == 1.0
    assert with_image.evidence['n_halo'] >= 0.9 * sc['halo'].sum()
    error = {
        (name, where): float(np.mean(np.abs(r.depth - sc['depth'])[mask]))
        for name, r in (('without', without), ('with', with_image))
        for where, mask in (('halo', sc['halo']), ('image', np.ones((H, W), dtype=bool)))
    }
    # Measured: the halo's pixels 1.16 m off -> 0.77 m (the box's own points still pull them),
    # the image 0.111 -> 0.100 m.
    assert error['with', 'halo'] < 0.75 * error['without', 'halo'], error
    assert error['with', 'image'] < 0.95 * error['without', 'image'], error


def test_the_halo_test_is_off_at_zero_and_a_negative_step_is_refused() -> None:
    sc = _scene()
    off = fuse_keyframe(sc['single'], sc['m'], None, FusionConfig(halo_min_step=0.0), image=sc['image'])
    assert off.evidence['halo_checked'] == 0.0
    with pytest.raises(ValueError, match='halo_min_step'):
        FusionConfig(halo_min_step=-0.1)


def test_a_region_the_single_view_has_off_is_kept_where_points_beyond_agree() -> None:
    """A poster on the wall: an image edge where the single view steps 25 % farther (its own
    error, a region off) while the wall is flat. The points on the poster's side of the edge
    look like a halo; the points further inside the poster carry the same depth, so the step is
    the single view's, and they stay. Without those points the test cannot tell, and drops."""
    yy, xx = np.mgrid[0:H, 0:W]
    depth = np.full((H, W), 3.0, dtype=np.float32)
    poster = (xx >= 20) & (xx < 70) & (yy >= 20) & (yy < 70)
    image = np.where(poster, 0.8, 0.3).astype(np.float32)
    single = np.exp(gaussian_filter(np.log(np.where(poster, 3.75, 3.0)), 1.5)).astype(np.float32)
    edge = (xx >= 18) & (xx < 22) & (yy >= 30) & (yy < 60)  # 2 px either side of the left border
    inside = (xx >= 25) & (xx < 30) & (yy >= 30) & (yy < 60)  # 5-9 px into the poster
    m = np.where(edge | inside, depth, np.nan).astype(np.float32)
    points = np.isfinite(m)
    assert not halo_points(image, single, m, points).any()
    alone = np.where(edge, depth, np.nan).astype(np.float32)
    assert halo_points(image, single, alone, np.isfinite(alone)).any()


def test_the_bench_row_times_the_test_on_a_fattened_box_scene() -> None:
    """``depth-fusion bench --only fusion`` prints the halo test's cost on a scene where it has
    work: most of the fattened points are flagged, and few others."""
    from depth_fusion_ros.bench.fusion import _halo_row

    row = _halo_row(160, 120, 5000, repeats=1, device='cpu')
    assert row.unit == 's' and 0 < row.value < 5
    flagged, found, wrong = (int(n) for n in re.findall(r'flagged (\d+), (\d+) of the (\d+)', row.note)[0])
    assert wrong > 50
    assert found >= 0.8 * wrong
    assert flagged - found <= 0.2 * flagged


def test_the_lookups_are_bilinear_and_split_into_calls_opencv_takes(monkeypatch) -> None:
    """``point_lookup.bilinear_at`` (``cv2.remap``), the halo test's lookup, against scipy's
    bilinear ``map_coordinates`` to float precision, off the image too (borders replicated),
    also when the samples are split over several calls (here 3 rows of 4 at most: OpenCV's maps
    stay under 32767 a side)."""
    from scipy.ndimage import map_coordinates

    from depth_fusion_ros import point_lookup

    rng = np.random.default_rng(5)
    image = gaussian_filter(rng.normal(size=(30, 40)), 2).astype(np.float32)
    x = rng.uniform(-3, 43, size=(50, 7)).astype(np.float32)
    y = rng.uniform(-3, 33, size=(50, 7)).astype(np.float32)
    reference = map_coordinates(image, np.stack((y.ravel(), x.ravel())), order=1, mode='nearest').reshape(
        x.shape
    )
    whole = point_lookup.bilinear_at(image, x, y)
    monkeypatch.setattr(point_lookup, 'ROW_WIDTH', 4)
    monkeypatch.setattr(point_lookup, 'MAX_ROWS', 3)
    split = point_lookup.bilinear_at(image, x, y)
    assert whole.shape == x.shape and np.array_equal(whole, split)
    # Exact weights (OpenCV 5; 1/32 px steps before): the torch twin of the halo test relies on it.
    assert np.abs(whole - reference).max() <= 1e-5
    assert point_lookup.bilinear_at(image, x[:0], y[:0]).shape == (0, 7)


def test_the_torch_halo_test_finds_the_same_points_as_numpy() -> None:
    """``occlusion_gpu.halo_points_torch`` (the fusion's halo test on a GPU) is the NumPy test
    step for step: the same points on every scene here, run on the CPU."""
    import torch

    from depth_fusion_ros.fusion.occlusion import gray_image
    from depth_fusion_ros.fusion.occlusion_gpu import halo_points_torch

    sc = _scene()
    scenes = [
        (sc['image'], sc['single'], sc['m'], np.isfinite(sc['m'])),
        (sc['image'], np.full((H, W), 2.5, dtype=np.float32), sc['m'], np.isfinite(sc['m'])),
        rendered_halo_keyframe(W, H),
    ]
    found = 0
    for image, single, m, points in scenes:
        expected = halo_points(image, single, m, points)
        got = halo_points_torch(gray_image(image), single, m, points, 0.1, torch.device('cpu'))
        np.testing.assert_array_equal(got, expected)
        found += int(expected.sum())
    assert found > 100
