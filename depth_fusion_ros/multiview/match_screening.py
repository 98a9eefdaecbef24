"""Matches at occlusion outlines dropped: patches that no single shift carries into the second image.

Why: a corner where a near object's outline crosses the background belongs to neither surface.
As the camera moves, it slides along the outline, so its match runs along the flow beyond where
either surface's point went (0.29 px on a rendered robot's stream, against 0.016 px for the
other matches). Every pair of a stream shares that error, so the mount check read it as a turn.
A level robot was turned 0.95 deg, and its tilted twin only 1.04 of 2 deg
(docs/multi_view.md, "Matches at occlusion outlines").

Such a patch holds two surfaces that move apart, so no single shift matches it in the second
image. Lucas-Kanade tracking from the first position, started at the match, leaves a larger
residual there: the mean absolute grey-level difference of the tracked window. On that stream
the residual ranked outline matches above the others with an AUC of 0.84. No depth is needed,
and the positions stay as matched. A match whose residual exceeds a multiple of its pair's
median is dropped: the multiple is relative because noise, blur and contrast set the level of
every residual of a pair alike.
"""

from __future__ import annotations

import cv2
import numpy as np

from .match_refinement import LK_CRITERIA, as_uint8

#: The compared window (px), at full resolution only: the match is already within a pixel or two.
WINDOW = (11, 11)


def patch_residuals(first: np.ndarray, second: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Per match ``p1 -> p2`` (M, 2) of two grey images: the mean absolute grey-level difference
    (0-255) between the window at ``p1`` and the window Lucas-Kanade tracks it to, started at
    ``p2``; ``inf`` where tracking failed."""
    if len(p1) == 0:
        return np.zeros(0)
    start = p1.astype(np.float32).reshape(-1, 1, 2)
    guess = p2.astype(np.float32).reshape(-1, 1, 2)  # a fresh array: OpenCV writes into it
    _, found, error = cv2.calcOpticalFlowPyrLK(
        as_uint8(first),
        as_uint8(second),
        start,
        guess,
        winSize=WINDOW,
        maxLevel=0,
        criteria=LK_CRITERIA,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    residual = error.ravel().astype(np.float64)
    residual[found.ravel() != 1] = np.inf
    return residual


def screen_matches(
    first: np.ndarray, second: np.ndarray, p1: np.ndarray, p2: np.ndarray, max_ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """The matches whose :func:`patch_residuals` is at most ``max_ratio`` times the median of the
    pair's finite ones (all of them when ``max_ratio`` is 0)."""
    if max_ratio <= 0 or len(p1) == 0:
        return p1, p2
    residual = patch_residuals(first, second, p1, p2)
    finite = np.isfinite(residual)
    if not finite.any():
        return p1[:0], p2[:0]
    keep = finite & (residual <= max_ratio * float(np.median(residual[finite])))
    return p1[keep], p2[keep]
