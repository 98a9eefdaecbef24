"""Is the camera mounted as the poses say? A check of the rotation between the told optical
frame and the camera's.

Why: a pose source gives the pose of its own frame (a body, an IMU, a motion-capture marker
set), and the optical frame is reached through a fixed transform someone measured or typed
(``camera_from_pose_frame``; a dataset's hand-eye calibration). A tilt of 1-2 degrees there is
easy to get and invisible downstream: every relative pose the multi-view depth triangulates
with is turned by it (the translation's direction in the camera, the rotation's axis), so
every depth is biased, smoothly, and the fusion's guard cannot see it because the points
still agree with each other. On TUM fr1_xyz the told poses fit the images best 1.5-1.75 deg
turned about the camera's x axis, and read that way the filter's depth is 22 % better
(docs/multi_view.md, "The mount check"). A principal point off by ``d`` pixels acts on the
depth, to first order, as a turn of ``d / f`` and is corrected with it.

:class:`MountCheck` takes the posed frames of a stream. A frame that moved ``min_baseline``
from the last sample is the next sample (a turn alone only when ``min_rotation_deg`` is set
under its 180); consecutive samples
make a pair (ORB, the images' own essential matrix keeps the matches of one rigid motion:
:mod:`.image_pairs`, as the other calibration checks; each match's second position tracked from
the first with an affine window, :mod:`.affine_tracking`). One rotation ``M`` (the camera's
frame in the told optical frame: ``T_wc = T_told @ M``) is fitted minimising the pairs' robust
Sampson costs (Levenberg-Marquardt over the rotation vector): at each new pair from
``early_pairs`` on, where only a turn sure at three standard errors ends the check, and at
``pairs``, the last look.

Before that fit, each look asks whether the told poses are of another frame altogether (a
body frame's, turned by whole axes: :mod:`.frame_fit`); such a turn, refined and confirmed on
the same cost, is the estimate instead (``MountEstimate.frame``).

What the motion leaves unobserved is not corrected: a translation along an axis says nothing
about a turn about that axis, and a turn about it leaves the depth as it is too. The fit's
covariance counts a pair as one piece of evidence (the sandwich of the pairs' own gradients:
an error of a told pose moves every match of its pair alike). A principal direction is
observed when its standard error is at most ``max_stderr_deg`` and a turn of 1 deg along it
from the fit raises the pairs' summed cost by at least ``min_cost_rise`` (1 %): where the cost
is flatter, an error every pair shares moves the fit more than any standard error shows (on
the synthetic robots driving ahead, the matches at depth edges, corners where an outline
crosses the background, slide along the flow by 0.3 px as the camera approaches; the pairs
agree on it, so neither the sandwich nor the jackknife sees it, and with matches only below a
high epipole it turned a level camera's fit by 1.8 deg). Such an error comes from what part
of the image shows (outlines, stripes, a checkered wall), so how sure a turn is also counts the
spread of the fit over the image: a jackknife over its four quadrants about the principal
point, which a turned mount moves alike and a local error does not. Along an observed direction
the fitted component is kept when it is more than twice its standard error (with that spread)
from zero, the others are zero. The verdict: ``disagrees`` when a kept component is at least
``threshold_deg`` beyond twice its standard error, ``unobservable`` when no direction is
observed, else ``consistent``. Pairs need decimetres of baseline (``min_baseline`` 0.1 m): at centimetres a
degree moves the matches' epipolar residuals by hundredths of a pixel on forward motion, and
the fit follows noise.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import ClassVar

import cv2
import numpy as np

from ..camera import PinholeCamera
from ..check_modes import CHECK_MODES, check_mode
from ..geometry import BODY_TO_OPTICAL, rotation_matrices
from .frame_fit import axis_rotations, gross_frame_turn, pairs_directions, snapped
from .image_pairs import (
    EARLY_STANDARD_ERRORS,
    STANDARD_ERRORS,
    MatchedPair,
    check_sampling,
    graded_verdict,
)
from .pair_stack import PairStack
from .paired_check import PairedCheck, feed
from .pose_inversion import InvertedPoses, direction_fit

log = logging.getLogger(__name__)

MOUNT_CHECK_MODES = CHECK_MODES

#: Finite-difference step of the cost's derivatives (radians; 0.05 deg).
_STEP = math.radians(0.05)
#: The largest step of one Levenberg-Marquardt iteration (radians) and the iterations allowed.
_MAX_STEP = math.radians(2.0)
_ITERATIONS = 40
#: The fit stops once a step is under this (radians).
_TOLERANCE = math.radians(0.002)
#: Blocks of consecutive pairs the jackknife leaves out one at a time.
_BLOCKS = 5
#: The most the fit may turn the told frame (degrees): beyond, the fit is refused as unobservable.
_MAX_TURN_DEG = 15.0
#: A whole frame's turn (``frame_fit.py``) is taken only when the pairs' summed cost at it is
#: this many times lower than at the told frame: on 7-Scenes given a body frame's poses it is
#: 35 times lower; on the ``repetitive`` stress case (seed 151) the images' own motion said a
#: 164 deg turn that raised the cost 40 times (matches on a repeated pattern).
FRAME_COST_GAIN = 4.0
#: The frame check looks from this many pairs on (the mount's own early look from
#: ``early_pairs``): a body frame's poses triangulate every keyframe with the wrong motion
#: until it is found. 7-Scenes 0-499 given them showed the turn from 3 pairs (frame 62) as
#: from 8 (frame 132); 108 stress streams of five seeds and 5 real variants told right
#: showed none at 3-8 pairs (docs/multi_view.md, "A straight drive, and an earlier look").
FRAME_EARLY_PAIRS = 3
#: Poses given inverted (``pose_inversion.py``) are looked for from this many pairs, on this
#: many directions: the inversion is not fitted (a frame turn is, 3 parameters), and the
#: matches' cost confirms it. Every keyframe before it is fused with points of the inverted
#: motion: the `forward` robot of seed 221 given inverted poses had 6 such keyframes (the
#: worst 2.96x its single view) with the inversion found at 4 pairs (frame 29).
INVERSION_EARLY_PAIRS = 2
INVERSION_MIN_DIRECTIONS = 2
#: From the first pair already when its matches fit the inverted poses this many times better
#: than the told ones (on one direction or more): one pair is all a low-texture room gave in
#: 100 frames (seed 221: 20.2 as told against 0.14 inverted). The first 4 pairs of 112 streams
#: told right fit the inverted poses at most 1.4 times better each, of ten told in a body frame
#: at most 4.9.
SINGLE_PAIR_COST_GAIN = 20.0
#: The 24 axis rotations as rotation vectors (radians): the frame turns tried on the pairs' cost
#: (read only: never written to).
_AXIS_ROTVECS = np.array([cv2.Rodrigues(R)[0].ravel() for R in axis_rotations()])
#: Which of them is the REP 103 body frame's turn (``frame_fit.BODY_TO_OPTICAL``); costs within
#: this share of each other fit alike (an axis rotation then wins over a refined turn, and the
#: REP 103 turn over other axis rotations).
_USUAL = int(np.argmin([np.abs(R - BODY_TO_OPTICAL).sum() for R in axis_rotations()]))
_ALIKE = 0.01
#: The turn (radians) along a principal direction at which ``min_cost_rise`` is read.
_RISE_TURN = math.radians(1.0)
#: The image is cut into this many columns and rows about the principal point for the regional
#: jackknife (:func:`regional_spread`), a match counted by its first position.
_REGIONS = 2
#: A pair keeps a region's leave-out only with this many matches left.
_MIN_REGION_MATCHES = 8


@dataclass(frozen=True)
class MountCheckConfig:
    """When to check the camera's mount rotation, and what to do when the images disagree."""

    #: off: no check; warn: check once and warn when the images and poses disagree with the
    #: told optical frame; correct: also turn the camera poses by the fitted rotation from then on
    mode: str = 'correct'
    #: A frame is the next image of a pair once it has moved this far from the last one (m)
    min_baseline: float = 0.1
    #: A frame is also the next image of a pair once it has turned this far from the last one
    #: (degrees; 180: by travel alone, as validated: a turn in place gives pairs without the
    #: baseline the fit needs)
    min_rotation_deg: float = 180.0
    #: Pairs of images the estimate uses (the check's last look; it ends there, once)
    pairs: int = 20
    #: Earlier looks, at each new pair from this many on (0, or pairs or more: none). One ends
    #: the check only when the mount surely disagrees by three standard errors, a stricter bar
    #: than the last look's two, for the extra looks; anything less waits for the next pair. A
    #: turned mount triples the multi-view error while the check collects, and 20 pairs take
    #: about 2 m of travel
    early_pairs: int = 8
    #: A disagreement counts when a fitted component less twice its standard error is at least
    #: this (degrees)
    threshold_deg: float = 0.5
    #: A direction of the rotation is observed when its standard error is at most this (degrees)
    max_stderr_deg: float = 0.3
    #: A direction is observed only when turning the fit 1 deg along it also raises the pairs'
    #: summed cost by this share: on a flatter cost a bias all the pairs share moves the fit
    #: further than its standard error says (0: the standard error alone decides)
    min_cost_rise: float = 0.01
    #: A match is dropped when the window at its first position, tracked into the second image,
    #: still differs from it by more than this multiple of the pair's median difference: a
    #: corner on an occlusion outline slides along the flow, and a bias all the pairs share
    #: turned a level robot 0.95 deg (multiview/match_screening.py; 0: every match kept, else at least 1)
    max_patch_residual: float = 2.0
    #: Matches a pair needs after RANSAC (and the screen above) to be used
    min_matches: int = 30
    #: ORB features per image
    features: int = 1000

    def __post_init__(self) -> None:
        object.__setattr__(self, 'mode', check_mode('mount_check', self.mode))
        check_sampling('mount_check', self)
        if not (0 < self.threshold_deg < 45 and self.max_stderr_deg > 0 and 0 <= self.min_cost_rise <= 1):
            raise ValueError(
                'mount_check: need 0 < threshold_deg < 45, max_stderr_deg > 0 and 0 <= min_cost_rise <= 1'
            )
        if not (self.max_patch_residual == 0 or 1 <= self.max_patch_residual <= 100):
            got = self.max_patch_residual
            raise ValueError(f'mount_check: max_patch_residual must be 0 (off) or in [1, 100], got {got}')


@dataclass(frozen=True)
class MountEstimate:
    """The fitted mount rotation of a stream and what it means for the told optical frame."""

    #: The correction kept (observed, significant components), as a rotation vector (degrees)
    #: of the camera's frame in the told optical frame: ``T_wc = T_told @ rotation``
    rotvec_deg: tuple[float, float, float]
    #: The whole fit, before its unobserved and insignificant components were dropped (degrees)
    fitted_deg: tuple[float, float, float]
    #: Standard errors of the fit along its principal directions (degrees, the regional spread
    #: counted), in the order of the pairs' own standard errors along them, smallest first
    stderr_deg: tuple[float, float, float]
    observed: int  # directions with a standard error within max_stderr_deg and the cost's rise
    pairs: int
    matches: int
    verdict: str  # 'consistent', 'suspect', 'disagrees', 'unobservable' or 'inverted' (pose_inversion.py)
    #: The camera axes (x, y, z) nearest the directions left unobserved, for the message
    unobserved_axes: tuple[str, ...] = ()
    #: The turn is a whole frame's (``frame_fit.py``: poses of a body frame given as the
    #: optical frame's), not a mount error
    frame: bool = False
    #: With the verdict ``inverted`` (``pose_inversion.py``): the median angles (degrees) between
    #: the images' directions and the told ones, as told and with the poses inverted
    inverted_residuals_deg: tuple[float, float] = (0.0, 0.0)

    @property
    def angle_deg(self) -> float:
        """The size of the correction (degrees)."""
        return float(np.linalg.norm(self.rotvec_deg))

    def rotation(self) -> np.ndarray:
        """The correction as a 4x4 transform (``T_wc = T_told @ this``); identity unless
        the verdict is ``disagrees``."""
        out = np.eye(4)
        if self.verdict == 'disagrees':
            out[:3, :3] = rotation_matrices(np.radians(np.asarray(self.rotvec_deg))[None])[0]
        return out

    def message(self) -> str:
        """One line for the log: the verdict with its numbers."""
        rv = ', '.join(f'{v:+.2f}' for v in self.rotvec_deg)
        sd = '/'.join(f'{s:.2f}' for s in self.stderr_deg)
        fit = f'{self.pairs} image pairs, {self.matches} matches, standard errors {sd} deg'
        if self.verdict == 'inverted':
            told, inverted = self.inverted_residuals_deg
            return (
                "mount check: the told poses fit the images inverted: they are the world's pose in the "
                "camera (T_cw, as a SLAM system keeps it), where camera/pose means the camera's pose in "
                f"the world (T_wc) (the images' motion {told:.0f} deg off the told one, {inverted:.0f} deg "
                f'off the inverted one, median over {self.observed} directions of {self.pairs} image pairs)'
            )
        if self.verdict == 'disagrees' and self.frame:
            return (
                f"mount check: the told poses are not of the camera's optical frame (x right, y down, "
                f'z forward): the images fit it turned {self.angle_deg:.1f} deg from them (rotation '
                f'vector [{rv}] deg in the camera frame; {fit}'
                + (
                    '; a straight drive: a turn about its direction is not seen, the axis rotation that '
                    'fits the direction taken (a REP 103 body frame where it fits)'
                    if self.observed < 3
                    else ''
                )
                + '): set camera_from_pose_frame (a body frame, x forward, is not the optical frame)'
            )
        if self.verdict == 'disagrees':
            return (
                f'mount check: the images and poses fit the camera turned {self.angle_deg:.2f} deg '
                f'from the told optical frame (rotation vector [{rv}] deg in the camera frame; {fit}): '
                'check camera_from_pose_frame (or the principal point)'
            )
        if self.verdict == 'suspect':
            return (
                f'mount check: the images and poses fit the camera turned {self.angle_deg:.2f} deg from '
                f'the told optical frame (rotation vector [{rv}] deg in the camera frame; {fit}), not '
                'surely: optical frame kept; check camera_from_pose_frame'
            )
        if self.verdict == 'unobservable':
            return (
                f'mount check: the motion does not pin the camera mount down ({fit}): optical frame kept, '
                'unchecked'
            )
        unseen = ''
        if self.unobserved_axes:
            axes = ', '.join(self.unobserved_axes)
            unseen = f'; a turn about {axes} is not checked: the motion or the matches do not pin it down'
        return (
            'mount check: the told optical frame agrees with the images and poses '
            f'({self.observed} of 3 directions observed; {fit}{unseen})'
        )


def _turns(rotvecs: np.ndarray) -> np.ndarray:
    """(S, 4, 4) transforms of rotation vectors (S, 3) (radians): made once per evaluation of all
    the pairs (scipy's conversion cost as much as a pair's costs)."""
    M = np.zeros((len(rotvecs), 4, 4))
    M[:, :3, :3] = rotation_matrices(rotvecs)
    M[:, 3, 3] = 1.0
    return M


def _stencil() -> np.ndarray:
    """The 19 offsets (radians) the value, gradient and Hessian are read from: the centre, ±h
    on each axis and the four (±h, ±h) on each pair of axes."""
    h, e = _STEP, np.eye(3)
    rows = [np.zeros(3)] + [s * h * e[i] for i in range(3) for s in (1, -1)]
    rows += [
        h * (s1 * e[i] + s2 * e[j])
        for i in range(3)
        for j in range(i + 1, 3)
        for s1 in (1, -1)
        for s2 in (1, -1)
    ]
    return np.array(rows)


_STENCIL = _stencil()


def _derivatives(costs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Values (P,), gradients (P, 3) and Hessians (P, 3, 3) from each of P pairs' costs at
    ``_STENCIL`` (19, P) (central differences)."""
    h = _STEP
    g = np.stack([(costs[1 + 2 * i] - costs[2 + 2 * i]) / (2 * h) for i in range(3)], axis=-1)
    H = np.zeros((costs.shape[1], 3, 3))
    for i in range(3):
        H[:, i, i] = (costs[1 + 2 * i] + costs[2 + 2 * i] - 2 * costs[0]) / h**2
    k = 7
    for i in range(3):
        for j in range(i + 1, 3):
            pp, pm, mp, mm = costs[k : k + 4]
            H[:, i, j] = H[:, j, i] = (pp - pm - mp + mm) / (4 * h * h)
            k += 4
    return costs[0], g, H


def _local(K: np.ndarray, stack: PairStack, v: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Total cost, per-pair gradients (P, 3) and total Hessian at rotation vector ``v``."""
    c, grads, H = _derivatives(stack.turned_costs(K, _turns(v + _STENCIL)))
    return float(c.sum()), grads, H.sum(axis=0)


def _totals(K: np.ndarray, stack: PairStack, rotvecs: np.ndarray) -> np.ndarray:
    """The pairs' summed cost (S,) at each of S rotation vectors (radians)."""
    return stack.turned_costs(K, _turns(rotvecs)).sum(axis=1)


def _total(K: np.ndarray, stack: PairStack, v: np.ndarray) -> float:
    return float(_totals(K, stack, v[None])[0])


def cost_rises(K: np.ndarray, pairs: list[MatchedPair], v: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Share (3,) by which the pairs' summed cost rises when the fit ``v`` is turned 1 deg along each
    unit column of ``directions`` (3, 3): the mean of the turns either way, over the cost at ``v``.

    Why a share and not a standard error: the standard errors come from the pairs' scatter, and
    an error the pairs share (matches at depth edges sliding along the flow) does not scatter. How
    far it moves the fit goes with the inverse of this curvature, so a flat direction is not
    read at all. Read over a whole degree rather than from the fit's Hessian (0.05 deg steps):
    the cost is not quadratic that far (on one tilted stream the Hessian said 9.4 %, the
    degree 3.5 %).
    """
    offsets = np.concatenate([np.zeros((1, 3)), _RISE_TURN * directions.T, -_RISE_TURN * directions.T])
    costs = _totals(K, PairStack.of(pairs), v + offsets)
    centre = max(float(costs[0]), 1e-12)
    return ((costs[1:4] + costs[4:7]) / 2.0 - centre) / centre


def _minimise(K: np.ndarray, stack: PairStack, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt from ``v`` on the eigenvalues of the summed Hessian (a flat direction
    moves only as far as its gradient pulls it, steps capped at 2 deg); the fit, the pairs'
    gradients and the summed Hessian there."""
    lam = 1e-3
    total, grads, hessian = _local(K, stack, v)
    for _ in range(_ITERATIONS):
        w, U = np.linalg.eigh(hessian)
        scale = max(float(w.max()), 1e-12)
        w = np.maximum(w, 1e-9 * scale)
        step = -U @ ((U.T @ grads.sum(axis=0)) / (w + lam * scale))
        norm = float(np.linalg.norm(step))
        if norm > _MAX_STEP:
            step *= _MAX_STEP / norm
        if _total(K, stack, v + step) < total:
            v = v + step
            lam = max(lam / 3.0, 1e-7)
            total, grads, hessian = _local(K, stack, v)
            if norm < _TOLERANCE:
                break
        else:
            lam *= 10.0
            if lam > 1e6:
                break
    return v, grads, hessian


def fit_mount(K: np.ndarray, pairs: list[MatchedPair]) -> tuple[np.ndarray, np.ndarray]:
    """The rotation vector (radians) that fits the pairs best and its covariance (3, 3).

    The covariance is the sum of two: the sandwich ``H^-1 B H^-1`` (``B`` the spread of the
    pairs' own gradients at the fit: pairs, not matches, are the independent evidence), and a
    jackknife over ``_BLOCKS`` blocks of consecutive pairs (the fit again without each). The
    sandwich alone was about 3x too confident on rendered streams (consecutive pairs share an
    image, and the cost is not quadratic over a degree): fits of one stream from samples 1-6
    frames later spread with a standard deviation of 0.28 deg where it said 0.1.
    """
    stack = PairStack.of(pairs)
    v, sandwich = _fit(K, stack)
    return v, sandwich + _block_spread(K, stack, v)


def _fit(K: np.ndarray, stack: PairStack) -> tuple[np.ndarray, np.ndarray]:
    """The best fit (radians) and its sandwich covariance (:func:`fit_mount`)."""
    v, grads, hessian = _minimise(K, stack, np.zeros(3))
    n = len(stack)
    inverse = np.linalg.pinv(hessian)
    return v, inverse @ (grads.T @ grads * (n / max(n - 1, 1))) @ inverse


def _block_spread(K: np.ndarray, stack: PairStack, v: np.ndarray) -> np.ndarray:
    """The jackknife covariance (3, 3) over blocks of consecutive pairs (:func:`fit_mount`): five
    fits more, most of a fit's cost."""
    blocks = np.array_split(np.arange(len(stack)), min(_BLOCKS, len(stack)))
    rest = [stack.keep(~np.isin(stack.pair, b)) for b in blocks]
    return _jackknife(np.array([_minimise(K, kept, v)[0] for kept in rest]))


def could_be_sure(v: np.ndarray, sandwich: np.ndarray, threshold: float, standard_errors: float) -> bool:
    """Whether fit ``v`` with sandwich covariance ``sandwich`` could still read as a turn of at
    least ``threshold`` (radians), sure at ``standard_errors``, once the jackknife is added.

    Why: a look needs the jackknife's five fits only when it could disagree, and the covariance
    they add can only make a turn less sure. A disagreeing component ``c`` along a unit ``u``
    has ``|c| >= threshold + k sd`` with ``sd^2 >= u^T S u``, so ``c^2 >= k^2 (u^T S u + eps)``
    for any ``eps <= threshold^2 / k^2``, and the most any ``u`` gives of ``c^2 / u^T (S + eps)
    u`` is ``v^T (S + eps)^-1 v``. Where that is under ``k^2``, or ``|v|`` is under the
    threshold, no look at the full covariance can disagree (a necessary condition only: the
    verdicts stay as they were, the looks cost less).
    """
    if float(np.linalg.norm(v)) < threshold:
        return False
    eps = 0.5 * (threshold / standard_errors) ** 2
    distance = float(v @ np.linalg.solve(0.5 * (sandwich + sandwich.T) + eps * np.eye(3), v))
    return distance >= standard_errors**2


def _jackknife(fits: np.ndarray) -> np.ndarray:
    """The delete-one jackknife covariance (3, 3) of fits (B, 3), each without one of B blocks."""
    spread = fits - fits.mean(axis=0)
    return spread.T @ spread * (len(fits) - 1) / len(fits)


def regional_spread(K: np.ndarray, pairs: list[MatchedPair], v: np.ndarray) -> np.ndarray:
    """A jackknife covariance (3, 3) of the fit over image regions: the fit again without the
    matches of each of ``_REGIONS`` x ``_REGIONS`` regions about the principal point.

    Why: an error the pairs share comes from what part of the view shows (corners at outlines,
    a striped or checkered wall), and the jackknife over pairs cannot see it. A turned mount
    moves every region's epipolar lines alike; a local error moves the fit only with its region's
    matches. On the synthetic robots, level ones fitted turns of up to 1.6 deg from such matches,
    sure at three standard errors by the pairs' own spread (docs/multi_view.md, "Matches tracked
    with an affine window").
    """
    stack = PairStack.of(pairs)
    regions = _regions(K, stack.p1)
    left = [stack.keep(regions != r, _MIN_REGION_MATCHES) for r in range(_REGIONS * _REGIONS)]
    fits = [_minimise(K, kept, v)[0] for kept in left if len(kept)]
    if len(fits) < 2:  # every match in one region: no spread over the image to read
        return np.zeros((3, 3))
    return _jackknife(np.array(fits))


def _regions(K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The region (row-major, ``_REGIONS`` x ``_REGIONS`` about the principal point) of each
    position (M, 2)."""
    column = np.clip(np.floor(points[:, 0] / (2.0 * K[0, 2] + 1.0) * _REGIONS), 0, _REGIONS - 1)
    row = np.clip(np.floor(points[:, 1] / (2.0 * K[1, 2] + 1.0) * _REGIONS), 0, _REGIONS - 1)
    return (row * _REGIONS + column).astype(int)


@dataclass
class MountCheck(PairedCheck):
    """Collects image pairs from a posed stream and checks the mount rotation once (see module)."""

    config: MountCheckConfig = field(default_factory=MountCheckConfig)
    result: MountEstimate | None = None
    TRACKING: ClassVar[str] = 'affine'
    #: Each pair's directions for the frame check (``frame_fit.pair_directions``), computed once
    #: for every look.
    _frame_directions: list = field(default_factory=list, repr=False)

    def _screen_ratio(self) -> float:
        return self.config.max_patch_residual

    def _estimate(self) -> MountEstimate:
        K = np.asarray(self.camera.K, dtype=np.float64)
        frame = self._frame_estimate(K)
        if frame is not None:
            return frame
        v, cov = fit_mount(K, self.pairs)
        return self._verdict(v, cov, regional_spread(K, self.pairs, v))

    def _frame_estimate(self, K: np.ndarray) -> MountEstimate | None:
        """Poses given inverted (``pose_inversion.py``, the verdict ``inverted``: no fit, so
        looked for first), else a whole frame's turn (``frame_fit.gross_frame_turn``), refined
        on the pairs' cost from there and taken as the axis rotation it is near
        (``frame_fit.snapped``), as a disagreement; None when the pairs show neither, or when
        the turn does not lower their cost ``FRAME_COST_GAIN`` times (the mount's own fit
        decides). Either must lower the pairs' cost that much; a turn that does not fit the
        matches ``FRAME_COST_GAIN`` times better than the inverted poses is taken as inverted
        poses (the directions fooled). What is left of a
        tilt is the next look's (the node starts the check over once it takes the turn)."""
        stack = PairStack.of(self.pairs)
        fit = direction_fit(pairs_directions(K, self.pairs, self._frame_directions))
        inverted = self._inversion(K, stack, fit, FRAME_COST_GAIN)
        if inverted is not None:
            return inverted
        turn = gross_frame_turn(K, self.pairs, self._frame_directions)
        if turn is None:
            return None
        # Along a line the cost is flat in the twist about it: the axis rotation as chosen.
        v = turn.rotvec if turn.along_line else _axis_or_refined(K, stack, turn.rotvec)
        turned_cost, told = _total(K, stack, v), _total(K, stack, np.zeros(3))
        if turned_cost * FRAME_COST_GAIN > told:
            return None  # the directions said a turn, the matches do not (a repetitive scene's)
        inverted = self._inverted_cost(K, stack) if fit is not None else math.inf
        if turned_cost * FRAME_COST_GAIN > inverted and inverted * FRAME_COST_GAIN <= told:
            # A turn fits 3 parameters to the pairs, the inversion none: a turn no clearly better
            # than the inverted poses is the directions fooled (handheld, seed 221: 80 deg at 2.67
            # against 3.03 inverted and 20.4 as told; a body frame's turn: 25-3000 times better).
            return self._inverted_estimate(fit)
        _, grads, hessian = _local(K, stack, v)
        inverse = np.linalg.pinv(hessian)
        n = len(stack)
        cov = inverse @ (grads.T @ grads * (n / max(n - 1, 1))) @ inverse
        sd = np.degrees(np.sqrt(np.maximum(np.diag(cov), 0.0)))
        degrees = tuple(float(x) for x in np.degrees(v))
        estimate = MountEstimate(
            degrees,  # type: ignore[arg-type]
            degrees,  # type: ignore[arg-type]
            tuple(float(x) for x in sd),  # type: ignore[arg-type]
            2 if turn.along_line else 3,
            n,
            sum(len(p.p1) for p in self.pairs),
            'disagrees',
            frame=True,
        )
        log.debug(
            '%s (directions %.1f deg off as told, %.1f turned)',
            estimate.message(),
            turn.told_residual_deg,
            turn.fit_residual_deg,
        )
        return estimate

    def _inversion_look(self, K: np.ndarray) -> MountEstimate | None:
        """The verdict ``inverted`` before the frame check's first look: the directions say it
        and the matches fit the inverted poses ``FRAME_COST_GAIN`` times better than the told
        ones, from ``INVERSION_EARLY_PAIRS`` pairs on ``INVERSION_MIN_DIRECTIONS`` directions, or
        ``SINGLE_PAIR_COST_GAIN`` times better from the first pair; else None."""
        single = len(self.pairs) < INVERSION_EARLY_PAIRS
        known = pairs_directions(K, self.pairs, self._frame_directions)
        fit = direction_fit(known, 1 if single else INVERSION_MIN_DIRECTIONS)
        gain = SINGLE_PAIR_COST_GAIN if single else FRAME_COST_GAIN
        return self._inversion(K, PairStack.of(self.pairs), fit, gain)

    def _inversion(
        self, K: np.ndarray, stack: PairStack, fit: InvertedPoses | None, gain: float
    ) -> MountEstimate | None:
        """The verdict ``inverted`` when the directions say it (``fit.says_inverted``) and the
        matches fit the inverted poses ``gain`` times better than the told ones; else None."""
        if fit is None or not fit.says_inverted:
            return None
        if self._inverted_cost(K, stack) * gain > _total(K, stack, np.zeros(3)):
            return None
        return self._inverted_estimate(fit)

    def _inverted_cost(self, K: np.ndarray, stack: PairStack) -> float:
        """The pairs' summed cost with their told poses inverted (``pose_inversion.py``)."""
        flipped = stack.with_poses(np.array([p.T_ba_inverted for p in self.pairs]))
        return _total(K, flipped, np.zeros(3))

    def _inverted_estimate(self, fit: InvertedPoses) -> MountEstimate:
        """The verdict ``inverted`` (nothing turned) with the directions' fit for its message."""
        zero = (0.0, 0.0, 0.0)
        residuals = (fit.told_residual_deg, fit.inverted_residual_deg)
        matches = sum(len(p.p1) for p in self.pairs)
        n = len(self.pairs)
        return MountEstimate(
            zero, zero, zero, fit.directions, n, matches, 'inverted', inverted_residuals_deg=residuals
        )

    def _early_look(self) -> MountEstimate | None:
        """At each new pair from ``early_pairs`` until ``pairs``: the estimate if the mount surely
        disagrees at ``EARLY_STANDARD_ERRORS``, else None (the check goes on). The frame check
        looks from ``FRAME_EARLY_PAIRS`` already, the inversion from the first pair
        (:meth:`_inversion_look`; ``early_pairs`` 0: no early look at all)."""
        n = self.config.early_pairs
        if not 0 < min(n, 1) <= len(self.pairs) < self.config.pairs:
            return None
        K = np.asarray(self.camera.K, dtype=np.float64)
        if len(self.pairs) < FRAME_EARLY_PAIRS:
            return self._inversion_look(K)
        frame = self._frame_estimate(K)
        if frame is not None or len(self.pairs) < n:
            return frame
        stack = PairStack.of(self.pairs)
        v, sandwich = _fit(K, stack)
        if not could_be_sure(v, sandwich, math.radians(self.config.threshold_deg), EARLY_STANDARD_ERRORS):
            return None
        cov = sandwich + _block_spread(K, stack, v)
        # The regional spread can only make a turn less sure (it adds to the standard errors
        # along the same directions), so it is fitted only for a look that is sure without it.
        if self._verdict(v, cov, standard_errors=EARLY_STANDARD_ERRORS).verdict != 'disagrees':
            return None
        estimate = self._verdict(v, cov, regional_spread(K, self.pairs, v), EARLY_STANDARD_ERRORS)
        return estimate if estimate.verdict == 'disagrees' else None

    def _verdict(
        self,
        v: np.ndarray,
        cov: np.ndarray,
        regional: np.ndarray | None = None,
        standard_errors: float = STANDARD_ERRORS,
    ) -> MountEstimate:
        """The estimate of fit ``v`` with covariance ``cov``: its principal directions say what
        is observed, and how sure each component is counts the ``regional`` spread as well (read
        along the same directions: that spread's own would mix a turn with what is unobserved)."""
        c = self.config
        w, U = np.linalg.eigh(0.5 * (cov + cov.T))
        observed = np.sqrt(np.maximum(w, 0.0)) <= math.radians(c.max_stderr_deg)
        total = cov if regional is None else cov + regional
        sd = np.sqrt(np.maximum(np.einsum('ij,ik,kj->j', U, total, U), 0.0))
        components = U.T @ v
        # A verdict read from a given fit and covariance without its pairs has no cost to read:
        # the standard errors alone decide. A fit that is not finite reads no rise.
        if c.min_cost_rise > 0 and self.pairs:
            K = np.asarray(self.camera.K, dtype=np.float64)
            observed &= cost_rises(K, self.pairs, v, U) >= c.min_cost_rise
        kept = observed & (np.abs(components) > standard_errors * sd)
        correction = U[:, kept] @ components[kept]
        margin = np.abs(components) - standard_errors * sd
        if not observed.any() or not np.isfinite(v).all() or np.degrees(np.linalg.norm(v)) > _MAX_TURN_DEG:
            verdict = 'unobservable'
        else:  # the largest kept component decides (none kept: nothing turned)
            size = float(np.abs(components[kept]).max(initial=0.0))
            sure = float(margin[kept].max(initial=-math.inf))
            verdict = graded_verdict(size, sure, math.radians(c.threshold_deg))
        estimate = MountEstimate(
            tuple(float(x) for x in np.degrees(correction)),  # type: ignore[arg-type]
            tuple(float(x) for x in np.degrees(v)),  # type: ignore[arg-type]
            tuple(float(x) for x in np.degrees(sd)),  # type: ignore[arg-type]
            int(observed.sum()),
            len(self.pairs),
            sum(len(p.p1) for p in self.pairs),
            verdict,
            _axes(U[:, ~observed]),
        )
        log.debug('%s', estimate.message())
        return estimate


def _axis_or_refined(K: np.ndarray, stack: PairStack, rotvec: np.ndarray) -> np.ndarray:
    """A whole frame's turn from the directions' fit ``rotvec``: refined on the pairs' cost and
    snapped (``frame_fit.snapped``), or the axis rotation of lowest cost where that fits the
    pairs at least as well. Why: from a Kabsch fit of nearly one line of directions the
    refinement stops in a local minimum (the ``translation`` robot told its body frame, seed
    171: 130 deg at a cost of 5.4 where the REP 103 turn costs 0.0), and frame conventions
    differ by whole axes. A turn off every axis rotation (a camera pitched on its body) keeps
    its refined fit, which costs less than any of them. Among axis rotations that fit alike
    (a twist about a straight drive's line costs nothing), the REP 103 turn is taken."""
    v = snapped(_minimise(K, stack, rotvec)[0])
    axes = _AXIS_ROTVECS
    costs = _totals(K, stack, axes)
    best = int(np.argmin(costs))
    if costs[_USUAL] <= costs[best] * (1.0 + _ALIKE) + 1e-12:
        best = _USUAL
    alike = costs[best] <= _total(K, stack, v) * (1.0 + _ALIKE) + 1e-12
    return axes[best].copy() if alike else v


def _axes(directions: np.ndarray) -> tuple[str, ...]:
    """The camera axis each column of ``directions`` lies nearest (x: a tilt, y: a pan, z: a roll)."""
    return tuple(sorted({'xyz'[int(np.argmax(np.abs(d)))] for d in directions.T}))


def check_frames(camera: PinholeCamera, frames: Iterable, config: MountCheckConfig) -> MountCheck:
    """A check fed with ``frames`` (anything with ``.gray`` and ``.pose``, in stream order)
    until it has its estimate (``.result``; ``None`` when they ran out first)."""
    return feed(MountCheck(camera, config), frames)  # type: ignore[return-value]


def turned(poses: np.ndarray, estimate: MountEstimate | None) -> np.ndarray:
    """Camera-to-world poses (N, 4, 4) read in the camera the estimate found (``T @ M``; as they
    are unless it disagrees: :meth:`MountEstimate.rotation`)."""
    return np.asarray(poses) if estimate is None else np.asarray(poses) @ estimate.rotation()
