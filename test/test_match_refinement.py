"""Matches tracked to sub-pixel (multiview/match_refinement.py): the second position follows
the first's patch under a zoom, where a detector's own positions carry a bias, and a wrong
match is dropped rather than moved."""

from __future__ import annotations

import cv2
import numpy as np

from depth_fusion_ros.multiview.match_refinement import MOVE_TOLERANCE_PX, as_uint8, refine_matches


def _texture(seed: int = 0, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random(size).astype(np.float32), (0, 0), 2.0)
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    return as_uint8(noise)


def test_tracked_positions_follow_a_zoom_to_a_tenth_of_a_pixel():
    """The second image is the first zoomed 4 % about (170.3, 115.7) and shifted: the kept
    matches land where the zoom takes their first positions, from starts up to 1.5 px off (a
    tenth of a pixel in the median, none beyond 0.3 px, no bias), and most are kept."""
    first = _texture()
    centre, zoom, shift = np.array([170.3, 115.7]), 1.04, np.array([0.37, -0.21])
    affine = np.hstack([zoom * np.eye(2), ((1 - zoom) * centre + shift)[:, None]])
    second = cv2.warpAffine(first, affine, (first.shape[1], first.shape[0]), flags=cv2.INTER_CUBIC)
    rng = np.random.default_rng(1)
    p1 = np.stack([rng.uniform(40, 280, 200), rng.uniform(40, 200, 200)], axis=1)
    truth = p1 @ affine[:, :2].T + affine[:, 2]
    start = truth + rng.uniform(-1.5, 1.5, truth.shape)
    kept1, kept2 = refine_matches(first, second, p1, start)
    assert len(kept1) >= 150
    expected = kept1 @ affine[:, :2].T + affine[:, 2]
    error = kept2 - expected
    assert np.median(np.linalg.norm(error, axis=1)) < 0.1 and np.abs(error).max() < 0.3
    assert np.abs(error.mean(axis=0)).max() < 0.02
    assert np.array_equal(kept1, p1[np.isin(p1[:, 0], kept1[:, 0])])  # first positions as given


def test_a_wrong_match_is_dropped_not_moved():
    """A match whose second position is on another patch (10 px away) is dropped: tracking it
    either lands far from where it started or does not come back."""
    first = _texture(2)
    p1 = np.array([[100.0, 100.0], [200.0, 120.0]])
    p2 = p1 + np.array([[0.4, -0.3], [10.0 + MOVE_TOLERANCE_PX, 0.0]])
    kept1, kept2 = refine_matches(first, first, p1, p2)
    assert kept1.tolist() == [[100.0, 100.0]]
    assert np.abs(kept2 - kept1).max() < 0.05
    empty = refine_matches(first, first, np.zeros((0, 2)), np.zeros((0, 2)))
    assert empty[0].shape == (0, 2)


def test_image_pairs_track_only_between_images_of_one_size():
    """A sample on another grid (a camera that changed its size) makes no tracked pair, and
    the one after it pairs again."""
    import math

    from depth_fusion_ros.multiview.image_pairs import ImagePairs

    K = np.array([[200.0, 0.0, 160.0], [0.0, 200.0, 120.0], [0.0, 0.0, 1.0]])
    pairs = ImagePairs(
        K, min_baseline=0.01, min_rotation_deg=2.0, min_matches=10, features=500, tracking='shift'
    )
    big = _texture(4, (480, 640))
    small = cv2.resize(big, (320, 240), interpolation=cv2.INTER_AREA)

    def pose(x: float) -> np.ndarray:
        T = np.eye(4)
        T[0, 3] = x
        return T

    assert pairs.add(big, pose(0.0)) is None  # the first sample
    assert pairs.add(small, pose(0.02)) is None  # another size: no pair, no error
    shifted = np.roll(small, 2, axis=1)
    pair = pairs.add(shifted, pose(0.04))
    assert (
        pair is not None
        and len(pair.p1) >= 10
        and math.isclose(float(np.median(pair.p2[:, 0] - pair.p1[:, 0])), 2.0, abs_tol=0.1)
    )
