"""Corrected keyframe poses from a pose source's corrected trajectory (a loop closure).

A SLAM that closes a loop re-estimates its past poses and publishes the corrected trajectory
(``nav_msgs/Path``: its own keyframes, each stamped). The map's keyframes are ours, at other
stamps, so the path cannot be read off at them. What varies smoothly along a trajectory is
the *correction* ``C(t) = T_new(t) T_old(t)^-1`` (a rigid motion of the world that a pose
graph optimisation spreads along the loop). So the correction is computed at each path stamp,
with the old pose there interpolated between our own keyframes' poses as they were
integrated, and interpolated (translation linear, rotation slerp) to each of our keyframes.
A keyframe at a path stamp takes the path's pose exactly.

What is not corrected, and why:

* keyframes after the path's last stamp: a pose source publishes after its correction in
  the corrected world, so those are right already (correcting them again would move them
  twice); except in a segment that a pose jump ended (below), which is all in the old world;
* keyframes before the path's first stamp: the path says nothing about them.

The keyframes' poses are camera poses; the path's are the pose source's own (its body frame,
at its clock). :func:`corrected_segments` with ``posings`` takes each keyframe to the pose source's frame
and time by the :class:`Posing` it was posed with (``camera_from_pose_frame``, turned by a mount
check, and the pose time offset), corrects it there and takes it back, so a correction of the
posing itself is kept through a loop closure instead of being undone by it.

One call corrects one *segment*: keyframes whose poses are in one world, stamps increasing.
The map node starts a new segment at each pose jump it notes and at a stream restart, and
corrects each on its own, so nothing is interpolated across a jump; a relocalised segment is
then moved into the corrected world by the path's poses in its own time span.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .geometry import interpolate_poses, invert_pose

#: Stamps closer than this (s) are the same instant (a path pose at one of our keyframes).
SAME_STAMP_S = 1e-4


@dataclass(frozen=True)
class CorrectionLimits:
    """Which corrections count (the smallest move, in metres or degrees), and the longest gap
    (s) between two of our poses that a pose of the corrected trajectory is compared across."""

    min_m: float = 0.01
    min_deg: float = 0.5
    max_gap: float = 2.0

    def counts(self, metres: float | np.ndarray, degrees: float | np.ndarray) -> bool | np.ndarray:
        """Whether a move (or each of several, as arrays) is large enough to count."""
        return (np.asarray(metres) >= self.min_m) | (np.asarray(degrees) >= self.min_deg)


@dataclass(frozen=True)
class Posing:
    """How a camera pose was read from the pose source: ``T_wc = T_pose(stamp + offset) @ T_pose_cam``.

    ``T_pose_cam``: the camera in the pose source's frame (``camera_from_pose_frame``, with a
    mount check's turn composed on); ``offset``: seconds from the image stamp to the pose
    source's time (``pose_time_offset`` plus a time offset check's correction)."""

    T_pose_cam: np.ndarray
    offset: float = 0.0


@dataclass(frozen=True)
class Corrections:
    """Per keyframe: its corrected pose (its old one where not corrected) and whether it was."""

    poses: np.ndarray  # (N, 4, 4)
    corrected: np.ndarray  # (N,) bool

    def moves(self, old: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Translation (m) and rotation (degrees) of each keyframe's correction, vectorised
        (the angle of ``R_new R_old^T``, as ``geometry.rotation_angle`` gives one)."""
        old = np.asarray(old, np.float64)
        metres = np.linalg.norm(self.poses[:, :3, 3] - old[:, :3, 3], axis=1)
        d = np.einsum('nij,nkj->nik', self.poses[:, :3, :3], old[:, :3, :3])  # R_new R_old^T
        # atan2 of the axis part and the trace: exact near 0, where arccos of the trace is not
        axis = np.stack((d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]), axis=1)
        trace = np.einsum('nii->n', d)
        degrees = np.degrees(np.arctan2(0.5 * np.linalg.norm(axis, axis=1), 0.5 * (trace - 1.0)))
        return metres, degrees


def _old_at(
    stamps: np.ndarray, poses: np.ndarray, query: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Our keyframes' (old) poses at ``query`` stamps: exact at a keyframe's stamp, else
    interpolated; invalid where the bracketing keyframes are more than ``max_gap`` s apart
    (the motion between them is not known well enough) or outside their span."""
    out, valid = interpolate_poses(stamps, poses, query)
    idx = np.clip(np.searchsorted(stamps, query, side='right') - 1, 0, len(stamps) - 1)
    nxt = np.minimum(idx + 1, len(stamps) - 1)
    valid &= stamps[nxt] - stamps[idx] <= max_gap
    for cand in (nxt, idx):  # a path pose at one of our keyframes: that keyframe's pose itself
        same = np.abs(stamps[cand] - query) <= SAME_STAMP_S
        out[same] = poses[cand[same]]
        valid |= same
    return out, valid


def corrected_poses(
    stamps: np.ndarray,
    poses: np.ndarray,
    path_stamps: np.ndarray,
    path_poses: np.ndarray,
    max_gap: float = 2.0,
    ended: bool = False,
) -> Corrections:
    """One segment's keyframe poses after the corrections a corrected trajectory implies.

    ``stamps`` (N,) strictly increasing (s), ``poses`` (N, 4, 4) camera-to-world as
    integrated; ``path_stamps`` (P,) and ``path_poses`` (P, 4, 4) the corrected trajectory,
    in any order. ``max_gap``: the longest gap (s) between two of our keyframes that an old
    pose is interpolated across. ``ended``: a later segment follows this one (a pose jump
    ended it: often the loop closure's own step), so all of it is in the old world and the
    poses after the path's last stamp take the correction there too.
    """
    stamps = np.asarray(stamps, np.float64)
    poses = np.asarray(poses, np.float64)
    out = poses.copy()
    corrected = np.zeros(len(stamps), dtype=bool)
    if len(stamps) == 0 or len(path_stamps) == 0:
        return Corrections(out, corrected)
    order = np.argsort(path_stamps, kind='stable')
    p_stamps = np.asarray(path_stamps, np.float64)[order]
    p_poses = np.asarray(path_poses, np.float64)[order]
    keep = np.concatenate(([True], np.diff(p_stamps) > SAME_STAMP_S))  # one pose per instant
    old, valid = _old_at(stamps, poses, p_stamps[keep], max_gap)
    p_stamps, p_poses, old = p_stamps[keep][valid], p_poses[keep][valid], old[valid]
    if len(p_stamps) == 0:
        return Corrections(out, corrected)
    fix = p_poses @ np.stack([invert_pose(T) for T in old])  # C = T_new T_old^-1 at each path stamp
    c, ok = interpolate_poses(p_stamps, fix, stamps)
    if ended:
        after = stamps > p_stamps[-1]
        c[after], ok[after] = fix[-1], True
    out[ok] = c[ok] @ poses[ok]
    corrected |= ok
    # A keyframe at a path stamp takes the path's pose itself (not one rounded through C).
    j = np.clip(np.searchsorted(p_stamps, stamps), 0, len(p_stamps) - 1)
    for cand in (j, np.maximum(j - 1, 0)):
        same = np.abs(p_stamps[cand] - stamps) <= SAME_STAMP_S
        out[same] = p_poses[cand[same]]
        corrected |= same
    return Corrections(out, corrected)


def corrected_segments(
    stamps: np.ndarray,
    poses: np.ndarray,
    segments: np.ndarray,
    open_segment: int,
    path_stamps: np.ndarray,
    path_poses: np.ndarray,
    max_gap: float,
    posings: list[Posing] | None = None,
) -> Corrections:
    """:func:`corrected_poses` of poses in several segments, each corrected on its own.

    ``stamps`` increase within each segment (in any order across them); ``segments`` (N,) the
    segment of each; ``open_segment`` the one still growing: every other segment was ended by
    a jump or a restart, so it is all in the old world (``ended``). ``posings``: the camera
    poses' own :class:`Posing` each, when the path is the pose source's poses
    (:func:`_through_posings`); None: the poses and the path are in the same frame and time."""
    if posings is not None:
        return _through_posings(
            stamps,
            poses,
            segments,
            posings,
            lambda *keyframes: corrected_segments(*keyframes, open_segment, path_stamps, path_poses, max_gap),
        )
    out = np.asarray(poses, np.float64).copy()
    corrected = np.zeros(len(out), dtype=bool)
    segments = np.asarray(segments)
    for segment in np.unique(segments):
        rows = np.nonzero(segments == segment)[0]
        fix = corrected_poses(
            np.asarray(stamps)[rows], out[rows], path_stamps, path_poses, max_gap, segment != open_segment
        )
        out[rows], corrected[rows] = fix.poses, fix.corrected
    return Corrections(out, corrected)


def _through_posings(
    stamps: np.ndarray,
    poses: np.ndarray,
    segments: np.ndarray,
    posings: list[Posing],
    correct: Callable[[np.ndarray, np.ndarray, np.ndarray], Corrections],
) -> Corrections:
    """``correct`` (stamps, poses, segments) of camera poses in the pose source's time and frame.

    Each keyframe (``stamps`` on the camera's clock, ``poses`` camera-to-world) goes there by its
    own :class:`Posing` (``stamp + offset``, ``T_wc @ T_pose_cam^-1``), is corrected and comes
    back (``@ T_pose_cam``). A path that restates the pose source's poses then moves nothing,
    whatever the posing added; a camera pose composed with a turn the pose source does not know
    keeps it. Within a segment the shifted stamps are put in order (an offset that changed can
    reorder two keyframes)."""
    stamps = np.asarray(stamps, np.float64)
    poses = np.asarray(poses, np.float64)
    segments = np.asarray(segments)
    if len(stamps) == 0:
        return Corrections(poses.copy(), np.zeros(0, dtype=bool))
    T_pc = np.stack([p.T_pose_cam for p in posings]).astype(np.float64)
    shifted = stamps + np.array([p.offset for p in posings], np.float64)
    told = poses @ np.linalg.inv(T_pc)
    order = np.lexsort((shifted, segments))
    fix = correct(shifted[order], told[order], segments[order])
    out, corrected = np.empty_like(poses), np.empty(len(stamps), dtype=bool)
    out[order] = fix.poses @ T_pc[order]
    corrected[order] = fix.corrected
    # Not corrected: exactly as it was (not rounded through the posing and back).
    out[~corrected] = poses[~corrected]
    return Corrections(out, corrected)


def new_world_from(stamp: float, path_end: float, newest_posed: float | None) -> float | None:
    """The first image stamp (s, the pose source's clock) in the corrected world, or ``None``:
    the next image posed, whatever its stamp.

    ``stamp`` is the corrected trajectory's header stamp, when the pose source corrected (0:
    not said); ``path_end`` its newest pose's stamp; ``newest_posed`` the newest image already
    posed at the old poses. Images stamped from ``stamp`` on get poses the source published
    after its correction; images on their way stamped before it (another topic, so their
    callback may come after the path's) get the old poses, as the frames already posed did,
    and belong with them. The next posed image is the boundary instead when the header says
    nothing new (unset, or not after ``newest_posed``), or when an image still to come lies
    within the path and so gets a corrected pose."""
    if stamp <= 0.0 or newest_posed is None or stamp <= newest_posed or path_end > newest_posed:
        return None
    return stamp
