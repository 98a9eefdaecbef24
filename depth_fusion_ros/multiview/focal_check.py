"""Does the camera's focal length agree with the images and the poses? A calibration check.

Why: a focal length 10 % off biases every multi-view depth by about as much, smoothly over the
image, and nothing downstream can tell (docs/fusion.md, "A known limit: a single view more
accurate in scale than the points"). With known poses the focal length is observable from the
images alone: a rotation between two views moves every pixel by about ``f`` times its angle,
and the epipolar geometry of the told relative pose fits the matched features best at the
true focal length (docs/multi_view.md, "The focal length check").

:class:`FocalCheck` takes the posed frames of a stream. A frame that has moved
``min_baseline`` or turned ``min_rotation_deg`` from the last sample (by the told poses) is
the next sample (ORB features), so a pair has the same signal at any speed and frame rate;
consecutive samples make a pair: their features are matched and the images'
own essential matrix (RANSAC) keeps the matches that fit one rigid motion, and each match's
second position is tracked from its first to sub-pixel (Lucas-Kanade). After ``pairs``
pairs, :func:`fit_pair_scale` fits one scale ``s`` of both focal lengths (principal point
kept) minimising the Sampson distances of the kept matches under the told relative poses,
pair by pair; their median is the estimate and their spread its standard error, once
(:func:`estimate_focal_scale`).
Motion that does not constrain the focal length, or poses too noisy to tell, give a large
one: ``unobservable``. The same pairs are fitted with a radial lens distortion too
(``lens_fit.py``), which reads as a focal error under rotation: the estimate says when the
images show one camera_info does not hold, and then no focal correction is applied: the lens is
taken instead (``data/lens_correction.py``), after ``lens_early_pairs`` pairs already when they
show it (:meth:`FocalCheck._early_look`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..camera import PinholeCamera
from ..check_modes import CHECK_MODES, check_mode
from .epipolar_cost import scaled_fundamentals, soft_l1_sampson
from .image_pairs import MatchedPair, check_sampling, graded_verdict
from .lens_fit import LensFit, fit_lens
from .paired_check import PairedCheck, feed

log = logging.getLogger(__name__)

FOCAL_CHECK_MODES = CHECK_MODES
VERDICTS = ('consistent', 'suspect', 'disagrees', 'unobservable')

#: The focal scales a fit may reach (a focal length half or twice the told one).
_SCALE_BOUNDS = (0.5, 2.0)

#: More than this share of the pairs fitting best at a bound of the range (:func:`censored`)
#: leaves the focal length unobservable, whatever the others say: one such pair of the
#: default 12 may be one bad pose, two say the poses do not fit the images.
MAX_CENSORED_SHARE = 0.1


#: What else reads as a focal error, for the warning: a lens distortion camera_info does not
#: hold bends the image outwards or inwards as a focal change would (the stress case
#: ``lens_distortion``: k1 -0.1 reads as +5 %), and a camera turned on its mount moves the
#: epipoles as one does.
CAUSES = (
    '(a lens distortion camera_info does not hold, or a camera mounted turned from '
    'camera_from_pose_frame, reads as a focal error too)'
)


@dataclass(frozen=True)
class FocalCheckConfig:
    """When to check the focal length, and what to do when the images disagree with it."""

    #: off: no check; warn: check once and warn when the images and poses disagree with the
    #: focal length; correct: also use the focal length they agree on for the multi-view depth
    #: and the keyframes' camera_info from then on, and undistort the images with a lens
    #: distortion they show
    mode: str = 'correct'
    #: A frame is the next image of a pair once it has moved this far from the last one (m)
    min_baseline: float = 0.05
    #: A frame is also the next image of a pair once it has turned this far from the last one (degrees)
    min_rotation_deg: float = 2.0
    #: Pairs of images the estimate uses (the check ends there, once)
    pairs: int = 12
    #: Pairs after which the check ends early when they already show a lens distortion
    #: (``LensFit.distorted``; 0, or pairs or more: never): the lens is then taken 16 frames
    #: sooner on the stress streams, and the focal length checked again on the undistorted images.
    #: A fit that already agrees there bounds the multi-view depth's focal uncertainty until
    #: the check ends (its offset plus two standard errors, ``focal_bias.focal_uncertainty``)
    lens_early_pairs: int = 8
    #: A disagreement counts when |log(fitted / told focal length)| less twice its standard
    #: error is at least this (0.05: surely more than 5 % off); a fit this far off but not
    #: surely is ``suspect``: warned, not corrected
    threshold: float = 0.05
    #: Standard error of the fitted scale above which the motion and the poses do not constrain
    #: it (the spread of the pairs' own fits, as a standard error of their median)
    max_stderr: float = 0.025
    #: Matches a pair needs after RANSAC to be used
    min_matches: int = 30
    #: ORB features per image
    features: int = 1000

    def __post_init__(self) -> None:
        object.__setattr__(self, 'mode', check_mode('focal_check', self.mode))
        check_sampling('focal_check', self)
        if not (0 < self.threshold < 1 and self.max_stderr > 0):
            raise ValueError('focal_check: need 0 < threshold < 1 and max_stderr > 0')
        if self.lens_early_pairs < 0:
            raise ValueError('focal_check: need lens_early_pairs >= 0')


@dataclass(frozen=True)
class FocalEstimate:
    """The fitted focal scale of a stream and what it means for the camera's calibration."""

    scale: float  # fitted / told focal length
    stderr: float
    pairs: int
    matches: int
    verdict: str  # one of VERDICTS
    told_fx: float
    told_fy: float
    #: The same pairs fitted with a radial lens distortion instead (``lens_fit.py``); None when
    #: not fitted.
    lens: LensFit | None = None
    #: Pairs whose fit lay at a bound of the scale range (:func:`censored`): too many of them
    #: make the estimate unobservable.
    censored: int = 0

    @property
    def fx(self) -> float:
        return self.told_fx * self.scale

    @property
    def fy(self) -> float:
        return self.told_fy * self.scale

    @property
    def poses_unfit(self) -> bool:
        """Whether too many pairs fit best at the end of the range (:func:`too_many_censored`):
        the told poses fit the images at no focal length."""
        return too_many_censored(self.censored, self.pairs)

    @property
    def lens_distorted(self) -> bool:
        """Whether the pairs fit a lens distortion camera_info does not hold (``LensFit.distorted``)."""
        return self.lens is not None and self.lens.distorted

    @property
    def lens_rivals(self) -> bool:
        """Whether a lens distortion fits the pairs about as well as the fitted focal change
        (``LensFit.rivals_focal``): a focal disagreement is then only ``suspect``."""
        return self.lens is not None and self.lens.rivals_focal

    def message(self) -> str:
        """One line for the log: the verdict with its numbers, and a lens distortion the images
        show."""
        text = self._verdict_message()
        return f'{text}; {self.lens.message()}' if self.lens_distorted else text

    def _verdict_message(self) -> str:
        fit = (
            f'the images and poses fit fx {self.fx:.1f} px best ({self.scale - 1:+.1%} +- {self.stderr:.1%}; '
            f'{self.pairs} image pairs, {self.matches} matches)'
        )
        if self.verdict == 'disagrees':
            told = f'camera_info says fx {self.told_fx:.1f} px'
            return f'focal length check: {told}, but {fit}: check the calibration {CAUSES}'
        if self.verdict == 'suspect' and self.lens_rivals and self.lens is not None:
            lens = f'k1 {self.lens.k1:+.3f} fits the pairs about as well (at {self.lens.cost_ratio:.2f}'
            return (
                f'focal length check: camera_info says fx {self.told_fx:.1f} px, but {fit}: a lens '
                f"distortion {lens} of the focal change's cost), so it is not surely the focal length: "
                f"fx {self.told_fx:.1f} px kept; check the calibration (the focal length, and the lens's "
                'distortion D)'
            )
        if self.verdict == 'suspect':
            return (
                f'focal length check: camera_info says fx {self.told_fx:.1f} px, but {fit}: past the '
                f'threshold by the fit, not surely: fx {self.told_fx:.1f} px kept; check the calibration '
                f'{CAUSES}'
            )
        if self.verdict == 'unobservable' and self.poses_unfit:
            return (
                f'focal length check: {self.censored} of {self.pairs} image pairs fit best at the end of '
                f'the range searched (half or twice fx {self.told_fx:.1f} px): their told poses fit '
                f'their images at no focal length (noisy poses, or poses of another frame than the '
                f'optical frame: camera_from_pose_frame): fx {self.told_fx:.1f} px kept, unchecked'
            )
        if self.verdict == 'unobservable':
            return (
                f'focal length check: the motion and poses do not pin the focal length down '
                f'({self.scale - 1:+.1%} +- {self.stderr:.1%} over {self.pairs} pairs): '
                f'fx {self.told_fx:.1f} px kept, unchecked'
            )
        return f'focal length check: fx {self.told_fx:.1f} px agrees with the images and poses: {fit}'

    def applied(self, mode: str, after_lens: bool = False) -> bool:
        """Whether the multi-view depth runs on the fitted focal length under ``focal_check.mode``
        ``mode``: only a sure disagreement is corrected, only in ``correct`` mode, and not when
        the pairs fit a lens distortion better (the lens is corrected instead and the focal
        length checked again on the undistorted images: ``data/lens_correction.py``).

        Nor ``after_lens``, on images undistorted with a fitted lens: what the fit leaves of the
        lens reads as a focal error too. A lens of -0.1 with a focal length 5 % short, fitted
        -0.085, left the check +12.2 % +- 1.7 % on a camera 5.3 % short, and the correction
        made the fusion 1.16x its input (0.996x without it; docs/fusion.md, "The lens taken")."""
        sure = self.verdict == 'disagrees' and not self.lens_distorted
        return mode == 'correct' and sure and not after_lens

    def corrected(self, camera: PinholeCamera) -> PinholeCamera:
        """``camera`` with both focal lengths scaled by the fitted scale (principal point kept)."""
        s = self.scale
        return PinholeCamera(camera.width, camera.height, camera.fx * s, camera.fy * s, camera.cx, camera.cy)


def _robust_costs(scales: np.ndarray, K: np.ndarray, pair: MatchedPair) -> np.ndarray:
    """Soft-L1 sum of one pair's Sampson distances at each of ``scales`` (S,)."""
    return soft_l1_sampson(scaled_fundamentals(scales, K, pair.T_ba), pair.p1, pair.p2).sum(axis=1)


#: The grid of focal scales every pair's cost is first evaluated on (1 % steps, log-spaced).
_GRID = np.exp(np.arange(math.log(_SCALE_BOUNDS[0]), math.log(_SCALE_BOUNDS[1]), 0.01))


def fit_pair_scale(pair: MatchedPair, K: np.ndarray) -> tuple[float, float]:
    """The focal scale that fits one pair's matches best under its told pose, and its soft-L1
    cost there (what the pair's best lens distortion is measured against: ``lens_fit.py``).

    The whole bounded range on a 1 % grid first, in one vectorised pass, then a bounded scalar
    search between the best step's neighbours: a local fit started at 1 stays near 1 where the
    cost is flat, and that would bias every weak pair towards the told focal length.
    """
    from scipy.optimize import minimize_scalar  # here: scipy.optimize imports scipy.spatial, which
    # costs a node process ~0.3 s before it is ready (test_node_modules_start_without_scipy)

    best = int(np.argmin(_robust_costs(_GRID, K, pair)))
    lo, hi = _GRID[max(best - 1, 0)], _GRID[min(best + 1, _GRID.size - 1)]
    fit = minimize_scalar(
        lambda x: float(_robust_costs(np.array([x]), K, pair)[0]), bounds=(lo, hi), method='bounded'
    )
    return float(fit.x), float(fit.fun)


def censored(scales: np.ndarray) -> np.ndarray:
    """Which pairs' fits (``scales``, :func:`fit_pair_scale`) lie within one grid step of a
    bound of the range: their cost still falls there, so the fit says only that the scale is
    at most half (or at least twice) the told one, not where it is.

    Why they are not estimates: the cost is a distance in pixels, and the error of a told
    relative pose is an angle, which a smaller focal length makes fewer pixels; where the
    pose's error outweighs the focal length's, the cost falls towards the range's lower end
    however the focal length is. On the wide-baseline keyframe
    stream with 5 mm and 0.3 deg of pose noise per keyframe (seed 161), 6 of 12 pairs fit 0.50:
    their median and its spread read -48 % +- 0.9 % and the node took fx 142 px for the
    true 262.5 (docs/multi_view.md, "Pairs at the range's end").
    """
    s = np.asarray(scales, dtype=np.float64)
    return (s <= _GRID[1]) | (s >= _GRID[-2])


def too_many_censored(n_censored: int, pairs: int) -> bool:
    """Whether ``n_censored`` of ``pairs`` pairs at a bound leave the focal length unobservable."""
    return n_censored > MAX_CENSORED_SHARE * pairs


def estimate_focal_scale(scales: np.ndarray) -> tuple[float, float]:
    """The focal scale the pairs agree on (the median of their own fits, ``scales``:
    :func:`fit_pair_scale`) and its standard error.

    Why per pair: an error of a told relative pose moves every match of that pair alike, so
    the matches of one pair are not independent evidence. One fit over all matches is biased
    by pose noise (a pose source with 4 mm and 0.25 deg of noise per frame pulled it to 0.80
    on an exact focal length) and its standard error, counted over matches, is far too small.
    The spread of the pairs' own fits says how much the poses let the images tell (the
    median absolute deviation, as a standard error of the median).
    """
    median = float(np.median(scales))
    if scales.size < 3:
        return median, math.inf
    spread = 1.4826 * float(np.median(np.abs(scales - median)))
    return median, spread * math.sqrt(math.pi / 2) / math.sqrt(scales.size)


@dataclass
class FocalCheck(PairedCheck):
    """Collects image pairs from a posed stream and checks the focal length once (see module)."""

    config: FocalCheckConfig = field(default_factory=FocalCheckConfig)
    result: FocalEstimate | None = None
    #: The early look's estimate when it agreed (``consistent``) and the check went on: what
    #: the filter's focal uncertainty is bounded by until the result (``focal_bias.py``).
    early: FocalEstimate | None = None
    #: Matches tracked to sub-pixel: the detector's own positions biased the fit under forward
    #: motion (-7.2 % on an exact focal length, corrected) and scattered it (multiview/match_refinement.py).
    TRACKING: ClassVar[str] = 'shift'

    def _estimate(self) -> FocalEstimate:
        """The pairs' fits and their median; more than ``MAX_CENSORED_SHARE`` of them at a
        bound of the range (:func:`censored`) make it unobservable (with the spread of all of
        them, what the filter's focal uncertainty then reads). Why not leave those pairs
        out instead: the pairs of the same noisy poses that fit inside the range are pulled
        towards its lower end as well (the SLAM keyframe stream of seed 5: 0.618 +- 0.042 with
        its two censored pairs, 0.631 +- 0.028 without them, all on a focal length 5 % long)."""
        K = self.camera.K
        scales, costs = zip(*(fit_pair_scale(p, K) for p in self.pairs), strict=True)
        fits = np.array(scales)
        n_censored = int(np.count_nonzero(censored(fits)))
        return self._verdict(*estimate_focal_scale(fits), fit_lens(self.pairs, K, list(costs)), n_censored)

    def _early_look(self) -> FocalEstimate | None:
        """At ``lens_early_pairs`` pairs: the estimate if they already show a lens distortion
        (the same rule as at the end: ``LensFit.distorted``), else None; an estimate that
        already agrees is kept as :attr:`early`. Why early: the node
        takes the lens and starts its history over, so every frame before that is seen through
        it. On the lens stress streams 8 pairs named it on 11 of 11 at 320x240 (frame 33 instead
        of 49); on the 48 other stress streams of seeds 0, 1 and 121 none came nearer than a
        cost ratio of 0.92 (0.85 names it; at 6 pairs a tilted mount came to 0.88)."""
        n = self.config.lens_early_pairs
        if not 0 < n < self.config.pairs or len(self.pairs) != n:
            return None
        estimate = self._estimate()
        if estimate.lens_distorted:
            return estimate
        if estimate.verdict == 'consistent':
            self.early = estimate  # not a verdict: the check goes on to its pairs
        return None

    def _verdict(
        self, scale: float, stderr: float, lens: LensFit | None = None, n_censored: int = 0
    ) -> FocalEstimate:
        unfit = too_many_censored(n_censored, len(self.pairs))
        if not math.isfinite(stderr) or stderr > self.config.max_stderr or scale <= 0 or unfit:
            verdict = 'unobservable'
        else:
            size = abs(math.log(scale))
            verdict = graded_verdict(size, size - 2.0 * stderr / scale, self.config.threshold)
        if verdict == 'disagrees' and lens is not None and lens.rivals_focal:
            # A lens camera_info does not hold reads as a focal error too; when it explains the
            # pairs about as well, correcting the focal length biases every depth instead
            # (lens_distortion seed 231: +6.9 % taken, the fusion 1.045x its input, lens_fit.py).
            verdict = 'suspect'
        matches = sum(len(p.p1) for p in self.pairs)
        estimate = FocalEstimate(
            scale, stderr, len(self.pairs), matches, verdict, self.camera.fx, self.camera.fy, lens, n_censored
        )
        log.debug('%s', estimate.message())
        return estimate


def check_frames(camera: PinholeCamera, frames: Iterable, config: FocalCheckConfig) -> FocalCheck:
    """A check fed with ``frames`` (anything with ``.gray`` and ``.pose``, in stream order)
    until it has its estimate (``.result``; ``None`` when they ran out first)."""
    return feed(FocalCheck(camera, config), frames)  # type: ignore[return-value]
