"""Matches tracked with an affine window (multiview/affine_tracking.py): the second position
follows the first's window under a zoom, a shear and a change of exposure, where a shifted
window is pulled off, and a match with nothing to track is dropped."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from test_match_refinement import _texture

from depth_fusion_ros.multiview.affine_tracking import (
    MOVE_TOLERANCE_PX,
    affine_templates,
    track_affine,
    track_templates,
)
from depth_fusion_ros.multiview.match_refinement import refine_matches


def _warped(first: np.ndarray, affine: np.ndarray, gain: float = 1.0, offset: float = 0.0) -> np.ndarray:
    """``first`` seen through ``affine`` (2x3, first-image to second-image positions), with its
    grey levels scaled by ``gain`` and raised by ``offset``."""
    second = cv2.warpAffine(first, affine, (first.shape[1], first.shape[0]), flags=cv2.INTER_CUBIC)
    return np.clip(second.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)


def _errors(affine: np.ndarray, kept1: np.ndarray, kept2: np.ndarray) -> np.ndarray:
    return np.linalg.norm(kept2 - (kept1 @ affine[:, :2].T + affine[:, 2]), axis=1)


def test_a_zoomed_sheared_darker_window_is_followed_to_a_few_hundredths_of_a_pixel():
    """The second image is the first zoomed 6 % and sheared 4 % about (170.3, 115.7), shifted,
    its contrast 0.8x and 20 grey levels brighter. From starts up to 1.5 px off, the kept
    matches land where the warp takes their first positions: 0.02 px in the median, none
    beyond 0.1 px. A shifted window is pulled off by the shear: 0.16 px in the median."""
    first = _texture()
    centre, shift = np.array([170.3, 115.7]), np.array([0.37, -0.21])
    linear = np.array([[1.06, 0.04], [0.0, 1.06]])
    affine = np.hstack([linear, (centre - linear @ centre + shift)[:, None]])
    second = _warped(first, affine, gain=0.8, offset=20.0)
    rng = np.random.default_rng(1)
    p1 = np.stack([rng.uniform(40, 280, 200), rng.uniform(40, 200, 200)], axis=1)
    start = p1 @ affine[:, :2].T + affine[:, 2] + rng.uniform(-1.5, 1.5, p1.shape)
    kept1, kept2 = track_affine(first, second, p1, start)
    assert len(kept1) >= 190
    error = _errors(affine, kept1, kept2)
    assert np.median(error) < 0.03 and error.max() < 0.1, (np.median(error), error.max())
    assert np.array_equal(kept1, p1[np.isin(p1[:, 0], kept1[:, 0])])  # first positions as given
    shifted1, shifted2 = refine_matches(first, second, p1, start)
    assert np.median(_errors(affine, shifted1, shifted2)) > 3 * np.median(error)


def test_a_match_with_nothing_to_track_or_too_far_is_dropped():
    """A window on a flat grey patch has no gradient to follow, and a start further than
    ``MOVE_TOLERANCE_PX`` from where the window went lands beyond it: both dropped; the
    textured match is kept where it belongs."""
    first = _texture(2)
    first[150:210, 230:300] = 128  # a flat patch
    p1 = np.array([[100.0, 100.0], [265.0, 180.0], [200.0, 60.0]])
    p2 = p1 + np.array([[0.4, -0.3], [0.4, -0.3], [MOVE_TOLERANCE_PX + 3.0, 0.0]])
    kept1, kept2 = track_affine(first, first, p1, p2)
    assert kept1.tolist() == [[100.0, 100.0]]
    assert np.abs(kept2 - kept1).max() < 0.02
    empty = track_affine(first, first, np.zeros((0, 2)), np.zeros((0, 2)))
    assert empty[0].shape == (0, 2) and empty[1].shape == (0, 2)


def test_windows_made_once_track_any_subset_as_a_fresh_call_would():
    """The pose refinement makes a keyframe's windows once and tracks a different subset of them
    into every frame: the same matches as tracking that subset from scratch."""
    first = _texture()
    affine = np.array([[1.03, 0.02, 1.4], [-0.01, 1.02, -0.8]])
    second = _warped(first, affine)
    rng = np.random.default_rng(3)
    p1 = np.stack([rng.uniform(40, 280, 120), rng.uniform(40, 200, 120)], axis=1)
    start = p1 @ affine[:, :2].T + affine[:, 2] + rng.uniform(-1.0, 1.0, p1.shape)
    templates = affine_templates(first, p1)
    subset = np.flatnonzero(rng.uniform(size=len(p1)) < 0.6)
    once = track_templates(templates, second, start[subset], subset)
    fresh = track_affine(first, second, p1[subset], start[subset])
    assert len(once.first) >= 0.9 * len(subset)
    assert np.array_equal(p1[subset][once.kept], once.first)  # which tracked points were kept
    assert np.array_equal(once.first, fresh[0]) and np.array_equal(once.second, fresh[1])
    whole = track_templates(templates, second, start)
    assert np.array_equal(whole[1], track_affine(first, second, p1, start)[1])


def test_windows_started_at_their_warps_converge_in_fewer_steps_to_the_same_place():
    """The pose refinement starts a frame's windows at the warps the previous frame's windows
    reached (``warps``). Started at the true warp, more windows have converged after two or
    three steps than from the identity, where the 6 % zoom and 4 % shear still move them (a
    window still moving is dropped). Given the steps they need, both starts land at the same
    positions (to a few thousandths of a pixel at the median; a window that stops within 0.01 px
    a step may stop a few hundredths apart), and the warps returned are the zoom and shear."""
    first = _texture()
    centre = np.array([170.3, 115.7])
    linear = np.array([[1.06, 0.04], [0.0, 1.06]])
    affine = np.hstack([linear, (centre - linear @ centre + np.array([0.37, -0.21]))[:, None]])
    second = _warped(first, affine)
    rng = np.random.default_rng(4)
    p1 = np.stack([rng.uniform(40, 280, 150), rng.uniform(40, 200, 150)], axis=1)
    start = p1 @ affine[:, :2].T + affine[:, 2] + rng.uniform(-0.3, 0.3, p1.shape)
    templates = affine_templates(first, p1)
    warps = np.tile(linear, (len(p1), 1, 1))
    kept = [
        [len(track_templates(templates, second, start, iterations=n, warps=w).first) for w in (warps, None)]
        for n in (2, 3)
    ]
    assert kept[0][0] > 2 * kept[0][1] and kept[1][1] < 0.9 * kept[1][0], kept
    warm = track_templates(templates, second, start, iterations=3, warps=warps)
    assert len(warm.first) >= 0.85 * len(p1)
    assert np.median(_errors(affine, warm.first, warm.second)) < 0.03
    both = track_templates(templates, second, start, warps=warps).kept
    both &= track_templates(templates, second, start).kept
    assert both.sum() >= 0.9 * len(p1)
    a = track_templates(templates, second, start[both], np.flatnonzero(both), warps=warps[both])
    b = track_templates(templates, second, start[both], np.flatnonzero(both))
    moved = np.linalg.norm(a.second - b.second, axis=1)
    assert np.median(moved) < 0.005 and moved.max() < 0.1, (np.median(moved), moved.max())
    assert np.abs(np.median(a.warps, axis=0) - linear).max() < 0.005
    with pytest.raises(ValueError, match='warps must be'):  # one warp per tracked point
        track_templates(templates, second, start, warps=warps[:-1])
