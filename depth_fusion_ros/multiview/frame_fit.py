"""Poses of another frame than the camera's: a turn of the told frame far beyond a mount error.

Why: ROS frames differ by whole axes. A pose source that publishes its body or IMU frame (x
forward, z up: REP 103) where the graph expects the optical frame (z forward, y down), with
``camera_from_pose_frame`` left out, turns every told relative pose by about 90-120 deg. The mount
check (``mount_check.py``) fits turns near the told frame only (its local fit from zero, refused
beyond ``_MAX_TURN_DEG``), so such a stream was triangulated with the wrong motion: 7-Scenes
0-499 given as a body frame's poses was fused to 1.04x its single view, and the adaptation,
trained on its points, made the single view 0.90 m against 0.48 m (docs/multi_view.md, "Poses
of another frame").

A frame turn shows in every pair without a fit of the cost: with the camera's frame ``M`` in
the told one (``T_wc = T_told @ M``), the images' own relative motion of a pair is the told
one seen from the turned frame, ``R_img = M^T R_told M`` and ``t_img ~ M^T t_told``. So the
rotation axes and the translation directions the images give (``cv2.recoverPose`` of the
pair's matches) are the told ones turned by ``M^T``: one rotation between two sets of unit
vectors (Wahba's problem, solved by an SVD: Kabsch). :func:`gross_frame_turn` returns it when
it is far from the identity and fits the pairs far better than the identity does; the mount
check then refines it on the pairs' own cost and takes it like a mount turn.

A straight drive gives one direction only (the translations, along one line; no rotation
axis), which leaves a turn about that line free: the rotation is not fixed. But while the
motion keeps to that line the free twist changes no triangulation, and the line itself is
told wrong by 90 deg or so with a body frame's poses (a robot told to drive sideways). A
forward robot with its body frame's poses was fused to 1.14x its single view (the `forward`
stress case, seed 171), and the check said nothing. So for one line :func:`line_frame_turn`
takes, among the axis rotations that carry the told line onto the seen one, the turn of
REP 103's body frame (x forward, z up) to the optical frame: the usual mistake. Any other it
takes only when it is the one axis rotation that fits. Where the robot turns later, the next
look (the node starts the check over) sees the rotation axis and corrects the twist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import BODY_TO_OPTICAL
from .image_pairs import RANSAC_SEED, MatchedPair

#: A turn smaller than this (degrees) is the mount check's own to fit: the same as its
#: ``_MAX_TURN_DEG``, beyond which it refuses a fit.
MIN_TURN_DEG = 15.0
#: The told frame must miss the images' directions by at least this (degrees, median over
#: them): a frame turned by whole axes misses them by 90-120, a right one by the directions' own
#: noise (7-Scenes 0-499: 12-18, most of it the translations of pairs that also turn)...
MIN_TOLD_RESIDUAL_DEG = 45.0
#: ... and the turned frame must fit them this many times better (the same noise: 9-21 deg on
#: 7-Scenes' body-frame poses after the turn, 96-116 before).
MIN_FIT_GAIN = 3.0
#: A pair's rotation axis counts when the images turn by at least this (degrees): below it the
#: axis is noise.
MIN_ROTATION_DEG = 2.0
#: Directions needed (axes and translations together) for a fit: two independent ones fix a
#: rotation, more make it a verdict (6 until 2026-12-05; 4 turned no stream told right of 108
#: stress streams and 5 real variants, and finds a straight drive's frame from 4 pairs).
MIN_DIRECTIONS = 4
#: The told directions must span two dimensions: their second singular value at least this
#: share of the first.
MIN_SPREAD = 0.2
#: A fitted turn this near (degrees) one that maps axes onto axes is taken as that one: frame
#: conventions differ by whole axes, and the fit is a few degrees off after 8 pairs (5.9 deg
#: on 7-Scenes' body-frame poses). A tilt of the camera on its body beyond it is left to the
#: mount check's next look.
SNAP_DEG = 10.0


@dataclass(frozen=True)
class FrameTurn:
    """The turn of the told frame that the pairs' directions fit (``T_wc = T_told @ M``)."""

    rotvec: np.ndarray  # (3,) radians, of M
    told_residual_deg: float  # median angle between the images' directions and the told ones
    fit_residual_deg: float  # the same after the turn
    directions: int
    #: The directions lie along one line (a straight drive): the turn about it is not seen,
    #: and the axis rotation taken is :data:`BODY_TO_OPTICAL` or the only one that fits.
    along_line: bool = False

    @property
    def angle_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(self.rotvec)))


def pair_directions(K: np.ndarray, pair: MatchedPair) -> Directions:
    """The told and the images' unit directions of one pair: its translation always, its
    rotation axis when the images turn by ``MIN_ROTATION_DEG`` or more; empty when the images'
    motion cannot be recovered. Third, the told ones again as they would be were the told poses
    inverted (the world's pose in the camera: ``pose_inversion.py``), one for each told one."""
    cv2.setRNGSeed(RANSAC_SEED)  # the same pair gives the same motion whatever ran before
    E, _ = cv2.findEssentialMat(pair.p1, pair.p2, K, cv2.RANSAC, 0.999, 1.0)
    if E is None or E.shape != (3, 3):
        return [], [], []
    _, R_img, t_img, _ = cv2.recoverPose(E, pair.p1, pair.p2, K)
    T, T_inv = pair.T_ba, pair.T_ba_inverted
    told, image, inverted = [], [], []
    t_told, t_seen, t_inv = T[:3, 3], t_img.ravel(), T_inv[:3, 3]
    if min(np.linalg.norm(t_told), np.linalg.norm(t_seen), np.linalg.norm(t_inv)) > 1e-9:
        told.append(t_told / np.linalg.norm(t_told))
        image.append(t_seen / np.linalg.norm(t_seen))
        inverted.append(t_inv / np.linalg.norm(t_inv))
    r_told, r_seen, r_inv = _rotvec(T[:3, :3]), _rotvec(R_img), _rotvec(T_inv[:3, :3])
    # Inverting the poses keeps each relative rotation's angle (R_b R_a^T against R_b^T R_a).
    if min(np.linalg.norm(r_told), np.linalg.norm(r_seen)) >= math.radians(MIN_ROTATION_DEG):
        told.append(r_told / np.linalg.norm(r_told))
        image.append(r_seen / np.linalg.norm(r_seen))
        inverted.append(r_inv / np.linalg.norm(r_inv))
    return told, image, inverted


#: A pair's told, images' and inverted-told directions (:func:`pair_directions`).
Directions = tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]


def pairs_directions(K: np.ndarray, pairs: list[MatchedPair], known: list[Directions]) -> list[Directions]:
    """The directions of each of ``pairs`` (:func:`pair_directions`): ``known`` holds those of
    the first pairs, kept by a caller that looks again at each new pair, and is extended with
    the others."""
    for pair in pairs[len(known) :]:
        known.append(pair_directions(np.asarray(K, dtype=np.float64), pair))
    return known[: len(pairs)]


def gross_frame_turn(
    K: np.ndarray, pairs: list[MatchedPair], known: list[Directions] | None = None
) -> FrameTurn | None:
    """The turn ``M`` of the told frame the pairs' directions fit (see module), or None when it
    is not a whole frame's: under ``MIN_TURN_DEG``, a told frame that misses the directions by
    less than ``MIN_TOLD_RESIDUAL_DEG``, a turn that fits them less than ``MIN_FIT_GAIN`` times
    better, or too few directions, or all of them along one line (``MIN_SPREAD``).

    ``known``: the directions of the first pairs (:func:`pair_directions`), kept by a caller
    that looks again at each new pair; it is extended with the others."""
    told, image = [], []
    for a, b, _ in pairs_directions(K, pairs, [] if known is None else known):
        told += a
        image += b
    if len(told) < MIN_DIRECTIONS:
        return None
    A, B = np.array(told), np.array(image)
    spread = np.linalg.svd(A, compute_uv=False)
    if spread[1] < MIN_SPREAD * spread[0]:
        return line_frame_turn(A, B)  # a straight drive: a turn about its line is free
    U, _, Vt = np.linalg.svd(A.T @ B)  # Kabsch: Q = argmin sum |b - Q a|^2, Q = M^T
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    Q = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    told_residual = median_angle_deg(A, B)
    fit_residual = median_angle_deg(A @ Q.T, B)
    turn = FrameTurn(_rotvec(Q.T), told_residual, fit_residual, len(told))
    if (
        turn.angle_deg < MIN_TURN_DEG
        or told_residual < MIN_TOLD_RESIDUAL_DEG
        or fit_residual * MIN_FIT_GAIN > told_residual
    ):
        return None
    return turn


def line_frame_turn(told: np.ndarray, seen: np.ndarray) -> FrameTurn | None:
    """The frame turn of directions along one line (see module): among the axis rotations that
    fit them ``MIN_FIT_GAIN`` times better than the told frame (which must miss them by
    ``MIN_TOLD_RESIDUAL_DEG``), :data:`BODY_TO_OPTICAL`, else the only one; None when none
    fits or several do and that one is not among them (the twist cannot be told)."""
    told_residual = median_angle_deg(told, seen)
    if told_residual < MIN_TOLD_RESIDUAL_DEG:
        return None
    fits = []
    for M in axis_rotations():
        residual = median_angle_deg(told @ M, seen)  # Q = M^T turns each told direction
        if residual * MIN_FIT_GAIN <= told_residual:
            fits.append((residual, M))
    usual = [f for f in fits if np.allclose(f[1], BODY_TO_OPTICAL)]  # REP 103: geometry.py
    if usual:
        residual, M = usual[0]
    elif len(fits) == 1:
        residual, M = fits[0]
    else:
        return None
    return FrameTurn(_rotvec(M), told_residual, residual, len(told), along_line=True)


def axis_rotations() -> np.ndarray:
    """The 24 rotations (24, 3, 3) that map the axes onto the axes (signed permutations of
    determinant 1): the turns between frame conventions."""
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            R = np.zeros((3, 3))
            R[range(3), perm] = [1.0 - 2.0 * k for k in signs]
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.array(out)


def snapped(rotvec: np.ndarray) -> np.ndarray:
    """``rotvec`` (radians) replaced by the nearest axis rotation (:func:`axis_rotations`) when
    that is within ``SNAP_DEG``, else as it is."""
    R = cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64).reshape(3, 1))[0]
    axes = axis_rotations()
    # The angle between R and each: from the trace of R^T A.
    cos = np.clip((np.einsum('ij,kij->k', R, axes) - 1.0) / 2.0, -1.0, 1.0)
    best = int(np.argmax(cos))
    if math.degrees(math.acos(cos[best])) > SNAP_DEG:
        return np.asarray(rotvec, dtype=np.float64)
    return _rotvec(axes[best])


def median_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = np.clip(np.einsum('ij,ij->i', a, b), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(cos))))


def _rotvec(R: np.ndarray) -> np.ndarray:
    v, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return v.ravel()
