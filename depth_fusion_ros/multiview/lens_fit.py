"""Do the focal check's matches fit a lens distortion better than a focal change? A diagnosis.

Why: a camera used without its lens calibration (camera_info with no distortion, images not
rectified) bends the image radially, and under rotation-dominant motion the multi-view depth
then fails (3.5-4x its error on the stress case ``lens_distortion``, docs/fusion.md "A lens
camera_info does not describe"). The focal check reads such a lens as a focal error, or as
nothing it can pin down, because a focal change and a radial distortion both move the points
away from the image centre. They differ in how: a focal change moves a point in proportion to
its distance from the centre, a distortion by its cube (plumb_bob ``xd = x (1 + k1 r^2)``).

So each pair of the focal check is fitted twice under its told relative pose: once with a focal
scale (as the check does) and once with a radial ``k1`` at the told focal length. The distortion
is reported when the pairs' median ``k1`` is at least :data:`MIN_K1` and the distortion explains
their matches clearly better than a focal change: the median over the pairs of its cost over the
focal fit's at most :data:`MAX_COST_RATIO`, with few pairs at the end of the ``k1`` range (a
pair that reaches the end was not constrained). On the stress case ``lens_distortion`` (``k1``
-0.1, the rotation sweep; seeds 0, 5, 81, 111) the pairs found -0.085 to -0.100 at a cost ratio
of 0.51-0.79. Every other stress case tried (seeds 0 and 1; the lateral sweeps, the rotation
sweep with a pinhole lens, blur, a rolling shutter, a walker, tiles, a tilted mount) stayed at
0.89 or above, and so did a lens seen on a lateral sweep (0.98: there its ``k1`` is not
observable, and it costs the depth little). In ``focal_check.mode`` correct the fitted ``k1``
is then added to the calibration the images are undistorted with (``data/lens_correction.py``;
since 2026-12-04, the sixty-fourth session: before, the lens was only said).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..radial_lens import undistort_radial
from .epipolar_cost import scaled_fundamentals, soft_l1_sampson
from .image_pairs import MatchedPair

#: The ``k1`` a pair may take (plumb_bob, normalised coordinates), on a 0.005 grid.
K1_GRID = np.round(np.arange(-0.3, 0.3 + 1e-9, 0.005), 3)
#: The smallest distortion reported (``k1`` -0.04 moves the corners of a 320x240 image by 4 px).
MIN_K1 = 0.04
#: The most a distortion's cost may be of the focal fit's (median over the pairs) to be reported.
MAX_COST_RATIO = 0.85
#: The largest share of the pairs whose best ``k1`` may lie at an end of the range.
MAX_AT_END = 1.0 / 3.0
#: The least a distortion's cost must be of the focal fit's (median over the pairs) for a focal
#: disagreement to be taken as one: below it a lens explains the pairs about as well, and the
#: focal check says so instead of correcting (``LensFit.rivals_focal``). Measured 2026-12-06 on
#: the stress streams' focal checks (docs/multi_view.md, "A lens that reads as a focal error"):
#: the six sure disagreements of a focal length 10 % long (``wrong_focal``, seeds 152-231) at
#: 1.27-1.73; the lens of ``lens_distortion`` seed 231, read as +6.9 % +- 0.7 %, at 1.03, and
#: a blurred lateral sweep's false -7.2 % (``motion_blur`` 231) at 0.93.
MIN_FOCAL_MARGIN = 1.15


@dataclass(frozen=True)
class LensFit:
    """The pairs' radial distortion: median ``k1`` and its standard error, the median over the
    pairs of its cost over their best focal scale's, and how many of the ``pairs`` reached an
    end of the ``k1`` range."""

    k1: float
    stderr: float
    cost_ratio: float
    at_end: int
    pairs: int

    @property
    def distorted(self) -> bool:
        """Whether the images show a lens distortion camera_info does not hold."""
        return (
            self.pairs >= 3
            and abs(self.k1) >= MIN_K1
            and self.cost_ratio <= MAX_COST_RATIO
            and self.at_end <= MAX_AT_END * self.pairs
        )

    @property
    def rivals_focal(self) -> bool:
        """Whether a lens distortion fits the pairs about as well as a focal change, without being
        reported (:attr:`distorted`): a focal disagreement is then not sure to be one."""
        return self.pairs >= 3 and not self.distorted and self.cost_ratio < MIN_FOCAL_MARGIN

    def message(self) -> str:
        return (
            f'the images fit a lens distortion k1 {self.k1:+.3f} +- {self.stderr:.3f} better than a focal '
            f'change (at {self.cost_ratio:.2f} of its cost, median of {self.pairs} pairs): give camera_info '
            "the lens's distortion (D) or rectified images"
        )


def _undistorted(p: np.ndarray, K: np.ndarray, k1: np.ndarray) -> np.ndarray:
    """Pixels ``p`` (N, 2) with each distortion of ``k1`` (S,) removed: (S, N, 2)."""
    x, y = undistort_radial((p[:, 0] - K[0, 2]) / K[0, 0], (p[:, 1] - K[1, 2]) / K[1, 1], k1[:, None])
    return np.stack((x * K[0, 0] + K[0, 2], y * K[1, 1] + K[1, 2]), axis=-1)


def _sampson_costs(K: np.ndarray, pair: MatchedPair, k1: np.ndarray) -> np.ndarray:
    """Soft-L1 sum of the pair's Sampson distances at the told focal length, each ``k1`` undone (S,)."""
    F = scaled_fundamentals(np.ones(1), K, pair.T_ba)
    return soft_l1_sampson(F, _undistorted(pair.p1, K, k1), _undistorted(pair.p2, K, k1)).sum(axis=1)


def fit_lens(pairs: list[MatchedPair], K: np.ndarray, scale_costs: list[float]) -> LensFit:
    """The pairs' ``k1`` (median of their own fits) and its standard error; ``scale_costs``: each
    pair's cost at its own best focal scale, which its best ``k1`` is measured against."""
    fits, ratios, at_end = [], [], 0
    for pair, scale_cost in zip(pairs, scale_costs, strict=True):
        costs = _sampson_costs(K, pair, K1_GRID)
        best = int(np.argmin(costs))
        fits.append(float(K1_GRID[best]))
        ratios.append(float(costs[best]) / max(scale_cost, 1e-12))
        at_end += int(best in (0, K1_GRID.size - 1))
    if not fits:
        return LensFit(0.0, math.inf, math.inf, 0, 0)
    k1, ratio = float(np.median(fits)), float(np.median(ratios))
    if len(fits) < 3:
        return LensFit(k1, math.inf, ratio, at_end, len(fits))
    spread = 1.4826 * float(np.median(np.abs(np.asarray(fits) - k1)))
    # The grid's step bounds how well one pair can fit, so the spread is not taken below it.
    spread = max(spread, float(K1_GRID[1] - K1_GRID[0]))
    return LensFit(k1, spread * math.sqrt(math.pi / 2) / math.sqrt(len(fits)), ratio, at_end, len(fits))
