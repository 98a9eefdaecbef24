"""A bounded, time-ordered buffer of poses that answers "where was the camera at t?".

SLAM systems publish poses at their own rate and stamps; images arrive at another. The
multi-view node keeps the recent poses here and asks for the pose at each image stamp.
No ROS import: stamps are float seconds.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from .geometry import interpolate_poses, validate_pose
from .pose_corrections import corrected_segments
from .pose_jumps import PoseJump, PoseJumpLimits, find_jump


@dataclass(frozen=True)
class PoseLookup:
    """Result of a look-up: the pose, or ``None`` with the reason it could not be given."""

    pose: np.ndarray | None
    reason: str = ''
    #: Counter key of a failed look-up: ``pose_gap`` (tracking lost, or outside the buffer)
    #: or ``pose_jump`` (between the two poses of a jump, :mod:`.pose_jumps`).
    key: str = 'pose_gap'


class PoseBuffer:
    """Keeps at most ``capacity`` poses sorted by stamp and interpolates between them.

    ``max_gap`` (s) bounds the interval a query may be interpolated across: a SLAM that
    lost tracking for two seconds must not produce a pose by slerping over the gap.
    ``jump_limits``: two consecutive poses further apart than these allow are a jump (a
    relocalisation): nothing is interpolated between them (:mod:`.pose_jumps`).
    """

    def __init__(
        self, capacity: int = 2000, max_gap: float = 0.5, jump_limits: PoseJumpLimits | None = None
    ) -> None:
        if capacity < 2:
            raise ValueError('pose buffer capacity must be at least 2')
        self.capacity = capacity
        self.max_gap = max_gap
        self.jump_limits = jump_limits or PoseJumpLimits(0.0, 0.0)
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []
        #: Stamps of the poses that follow a jump: no interpolation from the pose before them.
        self._after_jump: set[float] = set()

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def span(self) -> tuple[float, float] | None:
        """``(oldest, newest)`` stamp held, or ``None`` when empty."""
        return (self._stamps[0], self._stamps[-1]) if self._stamps else None

    def insert(self, stamp: float, pose: np.ndarray) -> PoseJump | None:
        """Add a pose (validated). Out-of-order stamps are placed in order; a duplicate stamp
        replaces the earlier pose. Raises ``PoseError``/``ValueError`` on a bad pose or stamp.

        Returns the jump this pose makes from the pose before it (or, placed out of order, to
        the pose after it), or ``None``.
        """
        if not np.isfinite(stamp):
            raise ValueError(f'pose stamp is not finite: {stamp}')
        pose = validate_pose(pose, 'pose')
        i = bisect.bisect_left(self._stamps, stamp)
        if i < len(self._stamps) and self._stamps[i] == stamp:
            self._poses[i] = pose
            return None
        self._stamps.insert(i, stamp)
        self._poses.insert(i, pose)
        jump = self._check_jumps(i)
        if len(self._stamps) > self.capacity:
            self._after_jump.discard(self._stamps[1])  # the pose before it goes
            del self._stamps[0]
            del self._poses[0]
        return jump

    def _check_jumps(self, i: int) -> PoseJump | None:
        """Mark the jumps between the new pose ``i`` and its neighbours in time."""
        found = None
        if i + 1 < len(self._stamps):  # it splits the interval before the next pose
            self._after_jump.discard(self._stamps[i + 1])
        for a in (i - 1, i):
            if a < 0 or a + 1 >= len(self._stamps):
                continue
            jump = self._jump_between(a)
            if jump is not None:
                self._after_jump.add(self._stamps[a + 1])
                found = found or jump
        return found

    def _jump_between(self, a: int) -> PoseJump | None:
        """The jump from pose ``a`` to pose ``a + 1``, or ``None``."""
        return find_jump(
            self.jump_limits, self._stamps[a], self._poses[a], self._stamps[a + 1], self._poses[a + 1]
        )

    def lookup(self, stamp: float) -> PoseLookup:
        """Pose at ``stamp`` (linear translation, slerp rotation) or the reason there is none."""
        if not self._stamps:
            return PoseLookup(None, 'no pose received yet')
        lo, hi = self._stamps[0], self._stamps[-1]
        if stamp < lo:
            return PoseLookup(None, f'stamp {stamp:.3f} is older than the pose buffer ({lo:.3f})')
        if stamp > hi:
            return PoseLookup(None, f'stamp {stamp:.3f} is newer than the latest pose ({hi:.3f})')
        i = bisect.bisect_left(self._stamps, stamp)
        if self._stamps[i] == stamp:
            return PoseLookup(self._poses[i].copy())
        gap = self._stamps[i] - self._stamps[i - 1]
        if gap > self.max_gap:
            return PoseLookup(None, f'pose gap of {gap:.3f} s around stamp {stamp:.3f}')
        if self._stamps[i] in self._after_jump:
            before, after = self._stamps[i - 1], self._stamps[i]
            reason = f'stamp {stamp:.3f} lies inside a pose jump ({before:.3f} -> {after:.3f} s)'
            return PoseLookup(None, reason, 'pose_jump')
        T, _ = interpolate_poses(
            np.array(self._stamps[i - 1 : i + 1]), np.stack(self._poses[i - 1 : i + 1]), np.array([stamp])
        )
        return PoseLookup(T[0])

    def reread(self, stamps: list[float], before: float, after: float) -> list[np.ndarray | None]:
        """The poses of frames stamped ``stamps`` (s, the camera's clock) that were posed at
        ``stamp + before``, read again at ``stamp + after``: a corrected time offset, applied
        backwards to what was posed before it (map_node re-poses its keyframes). ``None`` for a
        frame the buffer no longer covers at either time, or whose two times lie across a pose
        jump (the new pose would be in another world than the one it was mapped in)."""
        jumps = np.array(sorted(self._after_jump))
        out: list[np.ndarray | None] = []
        for stamp in stamps:
            lo, hi = sorted((stamp + before, stamp + after))
            across = bool(np.any((jumps > lo) & (jumps <= hi)))
            if across or self.lookup(stamp + before).pose is None:
                out.append(None)
            else:
                out.append(self.lookup(stamp + after).pose)
        return out

    def correct(
        self, path_stamps: np.ndarray, path_poses: np.ndarray, max_gap: float
    ) -> tuple[float, float] | None:
        """Move the poses as a corrected trajectory says (a loop closure:
        :mod:`.pose_corrections`), so that images still to be posed get poses in the corrected
        world. Each stretch between two jumps is a world of its own and is corrected on its own
        (a loop closure's step is often a jump: the poses before it are the ones the path
        moves, and the step goes). Returns how far (m, degrees) the newest pose the path covers
        moved: the step between the frames posed before and those to come; ``None`` when it
        covers none."""
        if not self._stamps:
            return None
        # Segment of each pose: how many jumps come at or before it.
        after = np.isin(np.array(self._stamps), np.array(sorted(self._after_jump)))
        segments = np.cumsum(after)
        old = np.stack(self._poses)
        fix = corrected_segments(
            np.array(self._stamps), old, segments, int(segments[-1]), path_stamps, path_poses, max_gap
        )
        if not fix.corrected.any():
            return None
        self._poses = list(fix.poses)
        self._after_jump.clear()  # the jumps again: a correction may remove a step (or make one)
        for a in range(len(self._stamps) - 1):
            if self._jump_between(a) is not None:
                self._after_jump.add(self._stamps[a + 1])
        metres, degrees = fix.moves(old)
        newest = int(np.nonzero(fix.corrected)[0][-1])
        return float(metres[newest]), float(degrees[newest])

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()
        self._after_jump.clear()
