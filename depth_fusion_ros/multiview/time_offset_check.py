"""Are the images and the poses stamped by the same clock? A time offset check.

Why: the multi-view depth measures baselines of millimetres to centimetres, and a hand-held
camera is 3.5 mm elsewhere 10 ms later. A camera driver that stamps an image on arrival
instead of exposure, or a pose source on another clock, shifts every told pose along the
motion. Shifting TUM fr1_xyz's poses by 10 ms raised the filter's median AbsRel from 6.7 % to
9.6-11.3 % (docs/nodes.md, "Clocks out of sync"), and nothing downstream can tell.

With known poses the offset is observable from the images alone, wherever the motion
accelerates or turns unevenly: the relative pose between two images, read from the pose
stream at ``t + d`` instead of ``t``, changes with ``d``, and the matched features fit the
epipolar geometry of the right one best. :class:`TimeOffsetCheck` takes the posed frames of a
stream (every frame's stamp and pose: the pose stream it interpolates in). A frame that moved
``min_baseline`` or turned ``min_rotation_deg`` from the last sample is the next sample;
consecutive samples make a pair (ORB features, the images' own essential matrix keeps the
matches that fit one rigid motion: :mod:`.image_pairs`, as the focal check). Once the stream has passed a
pair's second image by ``max_offset``, the pair's robust epipolar cost is evaluated for every
offset of a 2 ms grid over ``[-max_offset, max_offset]``; after ``pairs`` pairs the estimate is
the median of the pairs' best offsets and its standard error their spread, as the focal check
does. Smooth motion (constant velocity and turn rate) leaves every relative pose unchanged by
the offset, so the pairs' costs are flat, their best offsets scatter and the verdict is
``unobservable``: exactly where the offset does not matter to the depth either. An early look at
``early_pairs`` pairs ends the check sooner where the pairs already settle it (surely out of
sync, or flat), since an offset biases the multi-view depth until the check ends.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ..camera import PinholeCamera
from ..check_modes import CHECK_MODES, check_mode
from ..pose_curve import interpolate_poses_cubic
from .epipolar_cost import pose_costs
from .image_pairs import (
    EARLY_STANDARD_ERRORS,
    STANDARD_ERRORS,
    ImagePairs,
    MatchedPair,
    check_sampling,
    graded_verdict,
)

log = logging.getLogger(__name__)

TIME_OFFSET_CHECK_MODES = CHECK_MODES

#: Spacing of the offsets every pair's cost is evaluated at (s).
GRID_STEP = 0.002
#: Poses kept for the interpolation (every posed frame's; 5 min at 30 Hz).
_HISTORY = 9000
#: The pairs are drawn again with this seed for the standard error (a deterministic verdict).
_BOOTSTRAP_SEED = 2024
#: How far from the estimate its sharpness is read (s), and the least sharpness that fixes it:
#: the mean soft-L1 cost (at 0.5 px) rising by 0.02, about a tenth of a pixel of residual.
_SHARPNESS_AT = 0.02
_MIN_SHARPNESS = 0.02
#: At the early look, pairs whose cost rises less than this share of ``_MIN_SHARPNESS`` settle the
#: check as unobservable: the motion is so smooth that no offset matters to them. At 8 pairs of 87
#: recorded streams (docs/multi_view.md, "An early look at 8 pairs") 71 read 0.0043 or less, all
#: unobservable at 20 pairs too, and the 16 others 0.013 or more (the real sequences 0.023).
EARLY_FLAT_SHARE = 0.25


@dataclass(frozen=True)
class TimeOffsetCheckConfig:
    """When to check the image / pose time offset, and what to do when the images disagree."""

    #: off: no check; warn: check once and warn when the images fit poses read at another
    #: time; correct: also read the poses at the fitted offset from then on
    mode: str = 'correct'
    #: The offsets searched, either way (s)
    max_offset: float = 0.1
    #: A frame is the next image of a pair once it has moved this far from the last one (m;
    #: short pairs: the check is done after about 20 cm, and a pair spans the few hundred ms
    #: over which a hand changes its motion)
    min_baseline: float = 0.01
    #: A frame is also the next image of a pair once it has turned this far from the last one (degrees)
    min_rotation_deg: float = 0.5
    #: Pairs of images the estimate uses (the check ends there, once)
    pairs: int = 20
    #: An earlier look with this many pairs (0, or pairs or more: none). It ends the check only
    #: when the pairs already settle it: the images surely disagree by three standard errors
    #: (the last look: two), or the motion is so smooth that no offset matters (the pairs' cost
    #: rises by under a quarter of the least sharpness). Anything else waits for all the pairs.
    #: Until the check ends, an offset biases the multi-view depth and the mount check waits
    early_pairs: int = 8
    #: A disagreement counts when |fitted offset| less twice its standard error is at least
    #: this (s; 0.015: surely more than 15 ms off). On a real camera the fit itself is off by
    #: up to 10 ms (TUM fr1_xyz in sync reads -10 +- 2 ms), and a correction by that much
    #: would cost the depth as much as the offset it corrects
    threshold: float = 0.015
    #: Standard error of the fitted offset above which the motion does not constrain it (s)
    max_stderr: float = 0.004
    #: Matches a pair needs after RANSAC to be used
    min_matches: int = 30
    #: ORB features per image
    features: int = 1000

    def __post_init__(self) -> None:
        object.__setattr__(self, 'mode', check_mode('time_offset_check', self.mode))
        check_sampling('time_offset_check', self)
        if not (GRID_STEP <= self.max_offset <= 1.0):
            raise ValueError(f'time_offset_check: need {GRID_STEP} <= max_offset <= 1 s')
        if not (0 < self.threshold < self.max_offset and self.max_stderr > 0):
            raise ValueError('time_offset_check: need 0 < threshold < max_offset and max_stderr > 0')


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """The fitted offset of a stream: the images fit the poses read at ``stamp + offset`` best."""

    offset: float  # s, to add to the offset the poses were read with
    stderr: float
    pairs: int
    matches: int
    verdict: str  # consistent | suspect | disagrees | unobservable
    #: The offset the poses were read with (``pose_time_offset``)
    told: float = 0.0
    #: How much the pairs' mean cost rises 20 ms either side of the estimate (see estimate_offset)
    sharpness: float = 0.0

    @property
    def fitted(self) -> float:
        """The ``pose_time_offset`` the images fit best (s)."""
        return self.told + self.offset

    @property
    def flat(self) -> bool:
        """Whether the pairs fit every offset about alike (smooth motion; the verdict is then
        ``unobservable``): the fitted offset is wherever the noise put it, often the search's
        edge, and is not worth saying. The one test the log, the diagnostics and the report read."""
        return self.verdict == 'unobservable' and self.sharpness < _MIN_SHARPNESS

    def fit_phrase(self) -> str:
        """The fit in a few words: the offset and its standard error, or "flat"."""
        if self.flat:
            return f'flat over {self.pairs} pairs'
        return f'{self.offset * 1000:+.0f} +- {self.stderr * 1000:.0f} ms'

    def message(self) -> str:
        """One line for the log: the verdict with its numbers."""
        fit = (
            f'the images fit the poses {self.fit_phrase()} later best '
            f'({self.pairs} image pairs, {self.matches} matches)'
        )
        if self.verdict == 'disagrees':
            return (
                f'time offset check: {fit}: camera and pose source are out of sync; '
                f'pose_time_offset {self.fitted:.3f} fits them ({self.told:.3f} now)'
            )
        if self.verdict == 'suspect':
            return (
                f'time offset check: {fit}: off by the fit, not surely: pose_time_offset {self.told:.3f} '
                f'kept ({self.fitted:.3f} would fit best); check the clocks'
            )
        if self.flat:
            return (
                f'time offset check: the motion is too smooth to show an offset (the images fit every '
                f'offset alike over {self.pairs} pairs; none would matter to the depth either): '
                f'pose_time_offset {self.told:.3f} kept, unchecked'
            )
        if self.verdict == 'unobservable':
            return (
                f'time offset check: the motion does not pin the offset down ({self.fit_phrase()} over '
                f'{self.pairs} pairs): pose_time_offset {self.told:.3f} kept, unchecked'
            )
        return f'time offset check: pose_time_offset {self.told:.3f} agrees with the images: {fit}'


def pair_costs(
    K: np.ndarray, poses_a: np.ndarray, poses_b: np.ndarray, p1: np.ndarray, p2: np.ndarray
) -> np.ndarray:
    """Mean soft-L1 Sampson cost (S,) of matches ``p1 -> p2`` under each of S relative poses
    (the two images' camera-to-world poses ``poses_a``, ``poses_b``, (S, 4, 4)); ``inf`` where
    the two poses do not move (no epipolar geometry)."""
    return pose_costs(K, np.linalg.inv(poses_b) @ poses_a, p1, p2)


def estimate_offset(grid: np.ndarray, curves: np.ndarray, resamples: int = 200) -> tuple[float, float, float]:
    """The offset the pairs agree on, its standard error and how sharply it is fixed.

    ``curves`` (P, G): each pair's cost at every offset of ``grid``, less its own minimum. The
    estimate minimises their sum: a pair whose cost hardly changes with the offset (smooth
    motion over it) adds no pull, where its own best offset would be noise. The standard
    error is the spread of that minimum over pairs drawn again with replacement (seeded: the
    same pairs give the same verdict), because an error of a told pose moves every match of
    its pair alike, so a pair is one piece of evidence, not hundreds of matches. The sharpness
    is the mean rise of the pairs' cost ``_SHARPNESS_AT`` either side of the estimate (the
    smaller side): where the offset moves the matches' epipolar residuals by a tenth of a pixel
    or less, it does not matter to the depth either.
    """
    if len(curves) < 3:
        return 0.0, math.inf, 0.0
    best = int(np.argmin(curves.sum(axis=0)))
    rng = np.random.default_rng(_BOOTSTRAP_SEED)
    draws = rng.integers(0, len(curves), size=(resamples, len(curves)))
    weights = np.zeros((resamples, len(curves)))  # how often each pair was drawn, per resample
    np.add.at(weights, (np.arange(resamples)[:, None], draws), 1.0)
    resampled = grid[np.argmin(weights @ curves, axis=1)]
    stderr = max(float(np.std(resampled)), GRID_STEP / 2)
    reach = round(_SHARPNESS_AT / GRID_STEP)
    mean = curves.mean(axis=0)
    left, right = mean[max(best - reach, 0)], mean[min(best + reach, len(grid) - 1)]
    return float(grid[best]), stderr, float(min(left, right) - mean[best])


def shift_in_time(stamps: np.ndarray, poses: np.ndarray, offset: float) -> np.ndarray:
    """The poses of a stream read ``offset`` seconds later (``stamps`` increasing): along the
    cubic through the stream's own poses (:mod:`~depth_fusion_ros.pose_curve`), and at its ends
    extrapolated at the velocity of the end step (a stream's first and last frames keep a pose)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if offset == 0.0 or len(stamps) < 2:
        return poses.copy()
    t0 = stamps[0]
    out, valid = interpolate_poses_cubic(stamps - t0, poses, stamps + offset - t0)
    for i in np.flatnonzero(~valid):
        j = 0 if stamps[i] + offset < stamps[0] else len(stamps) - 2  # the end step
        out[i] = _extrapolate(stamps[j : j + 2], poses[j : j + 2], stamps[i] + offset)
    return out


def _extrapolate(stamps: np.ndarray, poses: np.ndarray, t: float) -> np.ndarray:
    """The pose at ``t`` on the line through two poses (translation linear in the world, rotation
    along their geodesic), past either end."""
    from scipy.spatial.transform import Rotation

    f = (t - stamps[0]) / max(stamps[1] - stamps[0], 1e-9)
    turn = Rotation.from_matrix(poses[0][:3, :3].T @ poses[1][:3, :3]).as_rotvec()
    out = np.eye(4)
    out[:3, :3] = poses[0][:3, :3] @ Rotation.from_rotvec(turn * f).as_matrix()
    out[:3, 3] = poses[0][:3, 3] + f * (poses[1][:3, 3] - poses[0][:3, 3])
    return out


@dataclass
class TimeOffsetCheck:
    """Collects image pairs from a posed stream and checks its time offset once (see module)."""

    camera: PinholeCamera
    config: TimeOffsetCheckConfig = field(default_factory=TimeOffsetCheckConfig)
    #: The offset the stream's poses were read with (reported, not applied)
    told: float = 0.0
    result: TimeOffsetEstimate | None = None
    frames: int = 0
    #: Each evaluated pair's cost over the offset grid (less its minimum) and its number of matches
    curves: list[tuple[np.ndarray, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._images = ImagePairs.for_config(self.camera.K, self.config)
        self._waiting: list[MatchedPair] = []  # matched, not yet covered by the pose history
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        self._grid = np.arange(-self.config.max_offset, self.config.max_offset + GRID_STEP / 2, GRID_STEP)
        self._looked = False  # the early look is taken once

    @property
    def done(self) -> bool:
        return self.result is not None or self.config.mode == 'off'

    @property
    def pairs(self) -> int:
        """Pairs matched so far (evaluated or waiting for the poses after them)."""
        return len(self.curves) + len(self._waiting)

    def observe(self, stamp: float, pose: np.ndarray) -> TimeOffsetEstimate | None:
        """Every posed frame's stamp and pose, in stream order (the poses the check reads at
        other times); returns the estimate once the last pair it needs is covered."""
        if self.done or (self._stamps and stamp <= self._stamps[-1]):
            return None
        self._stamps.append(float(stamp))
        self._poses.append(np.asarray(pose, dtype=np.float64))
        if len(self._stamps) > _HISTORY:
            del self._stamps[0], self._poses[0]
        return self._evaluate_covered()

    def wants(self, stamp: float, pose: np.ndarray, since: np.ndarray | None = None) -> bool:
        """Whether a frame at ``pose`` is the next sample: moved or turned enough since the last
        (or since the pose ``since``: a runner's last frame queued as a sample)."""
        return not self.done and self.pairs < self.config.pairs and self._images.far_enough(pose, since)

    def add(self, gray: np.ndarray, stamp: float, pose: np.ndarray) -> TimeOffsetEstimate | None:
        """One posed frame (grey image on this camera's grid): observed, and a sample when
        :meth:`wants` it; returns the estimate on the frame that completes it, else ``None``."""
        self.frames += 1
        if self.wants(stamp, pose):
            matched = self._images.add(gray, pose, stamp)
            if matched is not None:
                self._waiting.append(matched)
        return self.observe(stamp, pose)

    def _evaluate_covered(self) -> TimeOffsetEstimate | None:
        """Evaluate the waiting pairs the pose history now covers; the estimate once all are in."""
        if not self._stamps:
            return None
        newest, oldest = self._stamps[-1], self._stamps[0]
        reach = self.config.max_offset
        while self._waiting and self._waiting[0].b.stamp + reach <= newest:
            pair = self._waiting.pop(0)
            if pair.a.stamp - reach < oldest:
                continue  # its poses before the history: not evaluable
            self._evaluate(pair)
        if len(self.curves) < self.config.pairs:
            return self._early_look()
        return self._conclude(self._estimate())

    def _evaluate(self, pair: MatchedPair) -> None:
        # Only the poses the pair's reads reach, and two more each side for the cubic's tangents.
        reach = self.config.max_offset
        lo = max(bisect.bisect_left(self._stamps, pair.a.stamp - reach) - 2, 0)
        hi = bisect.bisect_right(self._stamps, pair.b.stamp + reach) + 2
        stamps = np.asarray(self._stamps[lo:hi])
        poses = np.asarray(self._poses[lo:hi])
        t0 = stamps[0]
        Pa, va = interpolate_poses_cubic(stamps - t0, poses, pair.a.stamp + self._grid - t0)
        Pb, vb = interpolate_poses_cubic(stamps - t0, poses, pair.b.stamp + self._grid - t0)
        if not (va.all() and vb.all()):
            return
        costs = pair_costs(self.camera.K, Pa, Pb, pair.p1, pair.p2)
        if np.isfinite(costs).all():
            self.curves.append((costs - costs.min(), len(pair.p1)))

    def _early_look(self) -> TimeOffsetEstimate | None:
        """Once ``early_pairs`` pairs are evaluated: the estimate if it already settles the check
        (surely out of sync at ``EARLY_STANDARD_ERRORS``, or flat: ``EARLY_FLAT_SHARE``), else None
        (the check goes on to ``pairs``). Pairs are evaluated a few at a time, as the poses after
        them come in, so the look is at the first count of at least ``early_pairs``."""
        n = self.config.early_pairs
        if self._looked or not 0 < n < self.config.pairs or len(self.curves) < n:
            return None
        self._looked = True
        estimate = self._estimate(EARLY_STANDARD_ERRORS)
        surely_flat = estimate.sharpness < EARLY_FLAT_SHARE * _MIN_SHARPNESS  # so unobservable too
        return self._conclude(estimate) if estimate.verdict == 'disagrees' or surely_flat else None

    def _estimate(self, standard_errors: float = STANDARD_ERRORS) -> TimeOffsetEstimate:
        """The estimate from the pairs evaluated so far; ``disagrees`` when the fitted offset less
        ``standard_errors`` of its standard error is at least the threshold."""
        curves = np.stack([c for c, _ in self.curves])
        offset, stderr, sharpness = estimate_offset(self._grid, curves)
        if not math.isfinite(stderr) or stderr > self.config.max_stderr or sharpness < _MIN_SHARPNESS:
            verdict = 'unobservable'
        else:
            sure = abs(offset) - standard_errors * stderr
            verdict = graded_verdict(abs(offset), sure, self.config.threshold)
        matches = sum(m for _, m in self.curves)
        return TimeOffsetEstimate(offset, stderr, len(curves), matches, verdict, self.told, sharpness)

    def _conclude(self, estimate: TimeOffsetEstimate) -> TimeOffsetEstimate:
        self.result = estimate
        log.debug('%s', self.result.message())
        self._waiting, self._stamps, self._poses = [], [], []
        self._images.reset()
        return self.result


def check_stream(
    camera: PinholeCamera, frames: Iterable, config: TimeOffsetCheckConfig, told: float = 0.0
) -> TimeOffsetCheck:
    """A check fed with ``frames`` (anything with ``.gray``, ``.stamp`` and ``.pose``, in stream
    order) until it has its estimate (``.result``; ``None`` when they ran out first)."""
    check = TimeOffsetCheck(camera, config, told)
    for frame in frames:
        if check.done or check.add(frame.gray, frame.stamp, frame.pose) is not None:
            break
    return check
