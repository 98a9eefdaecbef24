"""Points only on the single view's depth edges (fusion/edge_points.py), on scenes with exact truth.

The failure it mends (the stress case ``low_texture``, docs/fusion.md): a room with little
texture, posts in front of a wall, where the multi-view points lie on the silhouettes only, two
fifths of them halos (the post's depth on the wall's pixels). The single view is a good network's:
3 % too near over the image and blurred at the edges, so that at the points it reads the posts
too far. Every point then asks for a nearer depth than the wall needs.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from depth_fusion_ros.fusion.edge_points import edge_concentration, edge_explained
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import posts_keyframe

W, H = 320, 240
POSTS = [(40, 70), (120, 140), (200, 236), (270, 290)]  # x ranges of the posts (exclusive ends)
ROWS = (30, 210)


def _low_texture_keyframe() -> dict[str, np.ndarray]:
    scene = posts_keyframe(W, H, POSTS, ROWS, blur=2.0)
    return {'depth': scene.depth, 'single': scene.single, 'm': scene.multi}


def _mae(depth: np.ndarray, truth: np.ndarray) -> float:
    return float(np.nanmean(np.abs(depth - truth)))


def test_points_only_on_the_edges_no_longer_make_the_depth_worse_than_the_single_view() -> None:
    kf = _low_texture_keyframe()
    points = np.isfinite(kf['m'])
    share, ratio = edge_concentration(np.log(kf['single']), points)
    assert share > 0.9 and ratio > 3, 'the scene reproduces the concentration of the failing streams'
    single = _mae(kf['single'], kf['depth'])
    on = fuse_keyframe(kf['single'], kf['m'], None, FusionConfig())
    off = fuse_keyframe(kf['single'], kf['m'], None, FusionConfig(edge_ratio=0.0))
    assert _mae(off.depth, kf['depth']) > single, 'without the test the failure is reproduced'
    assert _mae(on.depth, kf['depth']) <= single
    assert on.evidence['edge_explained'] > 0.9
    assert on.evidence['edge_ratio'] == pytest.approx(ratio)
    assert 'edge_ratio' not in off.evidence


def test_points_spread_over_textured_surfaces_are_left_as_they_are() -> None:
    depth = _low_texture_keyframe()['depth']
    single = np.exp(gaussian_filter(np.log(depth * 1.2), 2.5)).astype(np.float32)
    m = np.full((H, W), np.nan, dtype=np.float32)
    m[::6, ::6] = depth[::6, ::6]
    points = np.isfinite(m)
    out, evidence = edge_explained(single, m, points, 2.8)
    assert out is m
    assert evidence['edge_ratio'] < 2.8 and evidence['edge_explained'] == 0.0
    fused = fuse_keyframe(single, m, None, FusionConfig())
    assert _mae(fused.depth, depth) < 0.5 * _mae(single, depth), 'the points correct the scale'


def test_a_point_beyond_the_edges_range_keeps_the_excess() -> None:
    kf = _low_texture_keyframe()
    points = np.isfinite(kf['m'])
    y, x = 120, POSTS[0][0]
    m = kf['m'].copy()
    m[y, x] = 1.1  # half the post's depth: no blur of the edge reaches it
    out, _ = edge_explained(kf['single'], m, points, 2.8)
    window = kf['single'][y - 5 : y + 6, x - 5 : x + 6]
    assert out[y, x] == pytest.approx(kf['single'][y, x] * 1.1 / window.min(), rel=1e-5)
    # a point within the range agrees with the single view
    assert out[y, x + 1] == pytest.approx(kf['single'][y, x + 1], rel=1e-6)


def test_a_point_on_a_non_positive_single_view_pixel_is_left_as_it_is() -> None:
    kf = _low_texture_keyframe()
    points = np.isfinite(kf['m'])
    y, x = 120, POSTS[0][0]
    single = kf['single'].copy()
    single[y, x] = -1.0  # a network's bad pixel
    out, evidence = edge_explained(single, kf['m'], points, 2.8)
    assert evidence['edge_explained'] > 0.9, 'the keyframe is still cut'
    assert out[y, x] == kf['m'][y, x]
    assert np.isfinite(out[points]).all() and (out[points] > 0).all()


@pytest.mark.parametrize('value', [-1.0, 0.5, float('nan'), float('inf')])
def test_a_bad_edge_ratio_is_a_one_line_error(value: float) -> None:
    with pytest.raises(ValueError, match='edge_ratio must be 0 \\(off\\) or a number >= 1'):
        FusionConfig(edge_ratio=value)
