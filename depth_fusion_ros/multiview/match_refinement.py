"""Feature matches made sub-pixel: the second image's position of each match tracked from the first.

Why: ORB places a keypoint wherever its detector fires in each image on its own (a corner
response at one of its pyramid levels, where positions are a level's pixel apart). When the two
images of a point differ in scale, as under forward motion, the differences of the two
positions carry a bias outward from the centre, and a fit of the focal length reads an outward
bias as a focal length that is too short: on a synthetic forward stream with an exact focal
length the focal check said -7.2 +- 1.0 % and corrected it (docs/multi_view.md, "Matches
tracked to sub-pixel"). Tracking the first position's patch into the second image (pyramidal
Lucas-Kanade, started at the matched keypoint) follows the same surface point, so that bias
goes, and so does most of the positions' scatter.
"""

from __future__ import annotations

import cv2
import numpy as np

#: The tracked patch (px) and the pyramid levels above the image Lucas-Kanade may use.
WINDOW = (15, 15)
LEVELS = 2
#: A tracked position is kept when tracking it back lands within this of where it started (px)...
BACK_TOLERANCE_PX = 0.5
#: ...and it is within this of the matched keypoint it started from (px): the match was right.
MOVE_TOLERANCE_PX = 3.0
#: When Lucas-Kanade stops iterating (also the outline screen's, match_screening.py).
LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)


def as_uint8(gray: np.ndarray) -> np.ndarray:
    """A grey image (float in [0, 1] or uint8) as uint8, as OpenCV's detectors and trackers take it."""
    if gray.dtype == np.uint8:
        return gray
    return np.clip(np.rint(np.asarray(gray, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def refine_matches(
    first: np.ndarray, second: np.ndarray, p1: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Matches ``p1 -> p2`` (M, 2) of two uint8 images with ``p2`` tracked from ``p1``: the
    matches Lucas-Kanade follows both ways (forward from ``p1``, started at ``p2``, and back)
    within :data:`BACK_TOLERANCE_PX`, and within :data:`MOVE_TOLERANCE_PX` of ``p2``; the rest
    are dropped. ``p1`` is kept as detected."""
    if len(p1) == 0:
        return p1, p2
    start = p1.astype(np.float32).reshape(-1, 1, 2)
    guess = p2.astype(np.float32).reshape(-1, 1, 2)
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    # The initial guesses are these fresh float32 arrays (OpenCV may write into them), not p1 / p2.
    tracked, found, _ = cv2.calcOpticalFlowPyrLK(
        first, second, start, guess, winSize=WINDOW, maxLevel=LEVELS, criteria=LK_CRITERIA, flags=flags
    )
    back, found_back, _ = cv2.calcOpticalFlowPyrLK(
        second, first, tracked, start, winSize=WINDOW, maxLevel=LEVELS, criteria=LK_CRITERIA, flags=flags
    )
    tracked, back = tracked.reshape(-1, 2), back.reshape(-1, 2)
    keep = (
        (found.ravel() == 1)
        & (found_back.ravel() == 1)
        & (np.linalg.norm(back - p1, axis=1) < BACK_TOLERANCE_PX)
        & (np.linalg.norm(tracked - p2, axis=1) < MOVE_TOLERANCE_PX)
    )
    return p1[keep], tracked[keep].astype(np.float64)
