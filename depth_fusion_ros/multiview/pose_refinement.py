"""Each posed frame's pose refined against the filter keyframe's image before it updates the filter.

Why: the filter triangulates with the poses it is told, and a SLAM's or a motion-capture
system's poses carry noise that the images can see. 0.3 deg of rotation noise moves an
epipolar line by 1.4 px at 320x240, 5 mm of position noise is a third of a hand's baseline
between two frames. On synthetic streams with that noise (5 mm and 0.3 deg per pose, as a
SLAM's), 22-70 % of the filter's published estimates were more than 10 % off their keyframe's
median error, against 6-11 % with exact poses, and the fusion took them where they agreed with
each other (docs/multi_view.md, "Poses refined against the keyframe"). The filter's own
estimates cannot correct the poses: they were measured with the same noisy poses, and an
alignment to them followed their errors (tried: a direct photometric alignment, the
relative rotation 0.25-1.3 deg off where the told one was 0.27-0.43).

How, per frame (:meth:`PoseRefiner.refine`):

1. The keyframe's corners (Shi-Tomasi, ``cv2.goodFeaturesToTrack``, found once per keyframe)
   are tracked into the frame by pyramidal Lucas-Kanade. The first frame after a keyframe
   starts each corner where the told pose puts it at the scene depth, which is pixels off
   where the depth is not the scene's: :data:`LK_LEVELS` pyramid levels. Every following
   frame starts each corner the previous frame kept where it was found there, moved by the
   told motion between the two frames (the previous one's refined pose to this one's told
   pose): off by the pose noise alone, about a pixel, and :data:`CHAINED_LEVELS` level above
   the image does (OpenCV's ``maxLevel``; Lucas-Kanade's cost on those frames falls by two
   thirds: docs/multi_view.md). A track is kept when tracking it back lands within
   :data:`BACK_TRACK_PX` of its corner; an affine window against the keyframe's then places it
   (``affine_tracking``: 0.02-0.03 px from the truth at the median on the synthetic streams),
   so that no error is carried from frame to frame. A frame that goes on from the previous one
   starts each window at the warp the previous frame's reached, so fewer steps converge. When
   fewer than :data:`CHAINED_SHARE` of the keyframe's corners are still tracked, the previous
   frame kept its told pose, or the camera moved too far since
   (:data:`CHAINED_PARALLAX_PX`), the frame starts over from the told pose; so does a frame
   whose tracks from the previous frame were too few.
2. The relative pose minimises the tracks' Sampson distances to their epipolar lines under a
   Cauchy loss (iteratively reweighted Gauss-Newton), plus a Gaussian prior at the told pose:
   ``filter.refine_sigma_deg`` on the rotation and ``filter.refine_sigma_m`` on the camera
   centre. The epipolar constraint needs no depth, and it cannot tell the baseline's length,
   nor, with a short baseline, a turn from a sideways step (the bas-relief ambiguity): the
   prior holds what the images do not say. The frame's pose is refined against the keyframe's
   (itself refined when it was a frame), its prior against its own told pose, so refinements
   never add up into a drift.

A frame whose tracks are too few (:data:`MIN_TRACKS`), or whose solution moved the pose by
more than :data:`MAX_SIGMAS` prior standard deviations, keeps its told pose (the filter
counts it: ``FilterStats.kept_told``).
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import cv2
import numpy as np

from ..camera import PinholeCamera
from ..geometry import invert_pose, rotation_angle, rotation_matrices, skews
from .affine_tracking import affine_templates, track_templates
from .epipolar_cost import sampson_distances
from .match_refinement import as_uint8

log = logging.getLogger(__name__)

#: A track counts only when tracking it back lands within this of its corner (px).
BACK_TRACK_PX = 0.3
#: Fewer tracks than this and the frame keeps its told pose.
MIN_TRACKS = 20
#: A solution that moved the pose further than this many prior standard deviations (rotation or
#: centre) is taken for a failure (tracks on a moving object, a repeated texture) and dropped.
MAX_SIGMAS = 6.0
#: Std of a track's position (px): the Sampson distances are divided by it.
TRACK_SIGMA_PX = 0.5
#: The Cauchy loss's scale, in those units: a track 0.5 px off its epipolar line weighs half.
CAUCHY_SCALE = 1.0
#: Lucas-Kanade: window, pyramid levels from the told pose's prediction and from the previous
#: frame's tracks, and stopping rule.
LK_WINDOW = (15, 15)
LK_LEVELS = 3
CHAINED_LEVELS = 1
LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
#: The affine window's Gauss-Newton steps: Lucas-Kanade has brought each track within a
#: fraction of a pixel, and 8 steps placed them as well as 20 (the same share of wrong estimates
#: on the synthetic streams and TUM, to 0.01) in 40 % of the time.
AFFINE_ITERATIONS = 8
#: Shi-Tomasi: quality relative to the best corner, and the least distance between corners (px).
CORNER_QUALITY = 0.01
CORNER_DISTANCE = 7
#: A frame goes on from the previous frame's tracks while they hold at least this share of the
#: keyframe's corners; fewer, and it tracks them all from the told pose again (the ones lost to a
#: blur or a passing occluder come back).
CHAINED_SHARE = 0.5
#: ...and while the camera moved so little since the previous frame that a point at half the
#: scene depth moves at most this much more than one at the scene depth (px): about half the
#: reach of Lucas-Kanade's window (15 px) at one pyramid level. The handheld streams, TUM and
#: 7-Scenes at 30 Hz move 0.5-4 px a frame so; a SLAM keyframe stream's 15 cm steps are 22 px,
#: and tracked from the previous frame their poses moved twice as far from exact ones.
CHAINED_PARALLAX_PX = 8.0


class PoseRefiner:
    """Refines frames' poses against the current keyframe's image (see the module's docstring)."""

    def __init__(self, camera: PinholeCamera, sigma_deg: float, sigma_m: float, corners: int) -> None:
        self.refocus(camera)
        self.sigma_rad = math.radians(sigma_deg)
        self.sigma_m = float(sigma_m)
        self.max_corners = int(corners)
        self._image: np.ndarray | None = None
        self._pose: np.ndarray | None = None
        self._corners = np.zeros((0, 2), dtype=np.float32)
        self._previous: _Tracks | None = None

    def refocus(self, camera: PinholeCamera) -> None:
        """Go on with ``camera``'s intrinsics (the focal check's correction)."""
        self.K = np.asarray(camera.K, dtype=np.float64)
        self.K_inv = np.linalg.inv(self.K)
        self._previous = None

    def keyframe(self, gray: np.ndarray, pose: np.ndarray) -> None:
        """The filter's new keyframe: its grey image (uint8, or float in [0, 1]), camera-to-world
        pose and corners. Until this returns, no frame is refined (a failure leaves the refiner
        without a keyframe, not with the last one)."""
        self._image = self._pose = self._previous = None
        image = as_uint8(gray)
        found = cv2.goodFeaturesToTrack(image, self.max_corners, CORNER_QUALITY, CORNER_DISTANCE, blockSize=5)
        self._corners = np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2)
        # What every frame tracked against this keyframe shares, made once: its corners'
        # affine windows.
        self._templates = affine_templates(image, self._corners.astype(np.float64))
        self._image, self._pose = image, np.asarray(pose, dtype=np.float64)

    def refine(self, gray: np.ndarray, told: np.ndarray, scene_depth: float) -> np.ndarray | None:
        """The frame's refined camera-to-world pose (its grey image uint8, or float in [0, 1]),
        or ``None`` where it keeps the told one (the filter counts it)."""
        if self._image is None or self._pose is None:
            return None
        T_fk_told = np.linalg.inv(told) @ self._pose
        previous, self._previous = self._previous, None
        if not self._chains(previous, len(self._corners), T_fk_told, scene_depth):
            previous = None
        frame = as_uint8(gray)
        tracks = self._track(frame, T_fk_told, scene_depth, previous)
        if tracks is None and previous is not None:  # too few went on: all of them from the told pose
            tracks = self._track(frame, T_fk_told, scene_depth, None)
        if tracks is None:
            return None
        solved = self._solve(self._corners[tracks.index].astype(np.float64), tracks.position, T_fk_told)
        if solved is None:
            return None
        pose = self._pose @ np.linalg.inv(solved)
        turn = math.degrees(rotation_angle(told[:3, :3].T @ pose[:3, :3]))
        shift = float(np.linalg.norm(pose[:3, 3] - told[:3, 3]))
        if turn > MAX_SIGMAS * math.degrees(self.sigma_rad) or shift > MAX_SIGMAS * self.sigma_m:
            log.debug('pose refinement dropped: moved %.2f deg, %.1f mm', turn, 1000 * shift)
            return None
        self._previous = tracks._replace(T_fk=solved)
        return pose

    def _track(
        self, frame: np.ndarray, T_fk: np.ndarray, scene_depth: float, previous: _Tracks | None
    ) -> _Tracks | None:
        """The keyframe's corners and where they are in ``frame``: LK from the previous frame's
        tracks (``previous``, where the frame goes on from them) or the told prediction, checked
        back, then placed by an affine window."""
        if len(self._corners) < MIN_TRACKS or frame.shape != self._image.shape:
            return None
        if previous is None:
            index, levels, warps = np.arange(len(self._corners)), LK_LEVELS, None
            guess = self._projected(index, T_fk, scene_depth)
        else:
            index, levels, warps = previous.index, CHAINED_LEVELS, previous.warps
            now, then = (self._projected(index, T, scene_depth) for T in (T_fk, previous.T_fk))
            guess = None if now is None or then is None else previous.position + now - then
        if guess is None:
            return None
        p0 = self._corners[index]
        start = np.ascontiguousarray(p0, dtype=np.float32).reshape(-1, 1, 2)
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        ahead, found, _ = cv2.calcOpticalFlowPyrLK(
            self._image, frame, start, np.ascontiguousarray(guess, dtype=np.float32).reshape(-1, 1, 2),
            winSize=LK_WINDOW, maxLevel=levels, flags=flags, criteria=LK_CRITERIA,
        )  # fmt: skip
        back, found_back, _ = cv2.calcOpticalFlowPyrLK(
            frame, self._image, ahead, start.copy(),
            winSize=LK_WINDOW, maxLevel=levels, flags=flags, criteria=LK_CRITERIA,
        )  # fmt: skip
        ahead, back = ahead.reshape(-1, 2), back.reshape(-1, 2)
        h, w = frame.shape
        ok = (found.ravel() == 1) & (found_back.ravel() == 1)
        ok &= np.linalg.norm(back - p0, axis=1) < BACK_TRACK_PX
        ok &= (ahead[:, 0] > 2) & (ahead[:, 0] < w - 3) & (ahead[:, 1] > 2) & (ahead[:, 1] < h - 3)
        if ok.sum() < MIN_TRACKS:
            return None
        found = track_templates(
            self._templates, frame, ahead[ok].astype(np.float64), index[ok], AFFINE_ITERATIONS,
            None if warps is None else warps[ok],
        )  # fmt: skip
        if len(found.first) < MIN_TRACKS:
            return None
        return _Tracks(index[ok][found.kept], found.second, found.warps)

    def _chains(self, previous: _Tracks | None, corners: int, T_fk: np.ndarray, depth: float) -> bool:
        """Whether the frame goes on from the previous frame's tracks: they hold at least
        :data:`CHAINED_SHARE` of the corners, and the camera moved so little since that a point at
        half the scene depth moves at most :data:`CHAINED_PARALLAX_PX` more than one at the
        scene depth (the start's error, beyond the pose noise, where the depth is unknown)."""
        if previous is None or len(previous.index) < CHAINED_SHARE * corners:
            return False
        moved = np.linalg.norm(invert_pose(T_fk)[:3, 3] - invert_pose(previous.T_fk)[:3, 3])
        return bool(self.K[0, 0] * moved / depth <= CHAINED_PARALLAX_PX)

    def _projected(self, index: np.ndarray, T_fk: np.ndarray, depth: float) -> np.ndarray | None:
        """Where keyframe-to-frame ``T_fk`` puts the corners ``index`` (M, 2, px) at ``depth``;
        ``None`` where one falls behind the camera."""
        p = self._corners[index].astype(np.float64)
        seen = T_fk[:3, :3] @ (self.K_inv @ np.vstack([p.T, np.ones(len(p))]) * depth) + T_fk[:3, 3:4]
        if np.any(seen[2] <= 0):
            return None
        return ((self.K @ seen)[:2] / seen[2]).T

    def _solve(self, p0: np.ndarray, p1: np.ndarray, T_fk_told: np.ndarray) -> np.ndarray | None:
        """The keyframe-to-frame transform that puts the tracks ``p0 -> p1`` (N, 2, px) on their
        epipolar lines, near the told one. Parameters: a turn of the frame (rotation vector) and a
        move of its centre in the keyframe's coordinates; iteratively reweighted Gauss-Newton for
        the Cauchy loss, the Jacobian by forward differences, all :data:`_PROBES` parameter sets
        in one pass (``epipolar_cost.sampson_distances`` takes them as a batch)."""
        moved = _MovedPose(T_fk_told)
        prior = np.array([self.sigma_rad] * 3 + [self.sigma_m] * 3)
        n = len(p0)
        p = np.zeros(6)
        for _ in range(SOLVER_STEPS):
            probes = p + _PROBES * (_STEP * prior)
            R, t = moved(probes)
            F = self.K_inv.T @ skews(t) @ R @ self.K_inv
            r = np.concatenate([sampson_distances(F, p0, p1) / TRACK_SIGMA_PX, probes / prior], axis=1)
            J = (r[1:] - r[0]) / (_STEP * prior)[:, None]  # (6, N + 6)
            w = np.ones(r.shape[1])
            w[:n] = 1.0 / (1.0 + (r[0, :n] / CAUCHY_SCALE) ** 2)
            H = (J * w) @ J.T
            g = (J * w) @ r[0]
            try:
                dp = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                return None
            p = p + dp
            if np.all(np.abs(dp) < 1e-3 * prior):
                break
        if not np.all(np.isfinite(p)):
            return None
        R, t = moved(p[None])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[0], t[0]
        return T


class _Tracks(NamedTuple):
    """A frame's tracks, and what the next frame starts from: which of the keyframe's corners,
    where they are in the frame, their windows' warps, and (once solved) the frame's refined
    keyframe-to-frame transform."""

    index: np.ndarray  # (N,) into the keyframe's corners
    position: np.ndarray  # (N, 2) px in the frame
    warps: np.ndarray  # (N, 2, 2): each corner's window, keyframe -> frame (affine part)
    T_fk: np.ndarray | None = None


class _MovedPose:
    """The told keyframe-to-frame transform moved by parameter sets (K, 6): a turn of the frame
    (rotation vector, left-multiplied) and a move of its centre in the keyframe's coordinates."""

    def __init__(self, T_fk_told: np.ndarray) -> None:
        self.R0 = T_fk_told[:3, :3]
        self.centre = -self.R0.T @ T_fk_told[:3, 3]

    def __call__(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (K, 3, 3) and translations (K, 3) of the moved transforms."""
        R = rotation_matrices(params[:, :3]) @ self.R0
        return R, -np.einsum('kij,kj->ki', R, self.centre + params[:, 3:])


#: The solver's steps at most, and its forward-difference step (in prior standard deviations).
SOLVER_STEPS = 15
_STEP = 1e-4
#: The solution and one probe per parameter.
_PROBES = np.vstack([np.zeros(6), np.eye(6)])
