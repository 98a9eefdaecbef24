"""map_node's side of multi_view_node's posing (nodes/posing.py): how each keyframe was posed,
and the keyframes it moves when multi_view_node's checks change that posing while it runs.

* **A mount turn** (``camera_from_pose_frame`` changed): the turn held for the whole run,
  also before the check found it, so every keyframe posed in the old transform (kept, waiting
  in the consistency window, the pose-jump test's last pose, or still in flight) is re-posed
  in the new one, ``T_wc @ old^-1 @ new``, and the map rebuilt from the kept ones.
* **A time offset correction** (``pose_time`` changed): the keyframes posed before it were
  read at the old offset. Only multi_view_node still has the pose source's poses around them:
  it reads them again at the new offset and publishes them (``reposed_keyframes``). The map
  node moves those keyframes there, in the same places, and rebuilds. Their depth stays as
  the old poses made it.

Without this, the map kept the first stretch of a run at the poses of a wrong time offset
or mount (the checks find them only after seconds of travel) and smeared it under the rest.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from ..data import messages
from ..geometry import rotation_angle
from ..pose_corrections import Corrections, Posing
from .corrected_path import path_poses
from .posing import PosingLog

T = TypeVar('T')

if TYPE_CHECKING:
    from .map_corrections import MapCorrector
    from .map_node import MapNode


class MapPosing:
    """The posings heard (:class:`PosingLog`) and what a change of them moves in a :class:`MapNode`."""

    def __init__(self, node: MapNode, corrector: MapCorrector) -> None:
        self.node = node
        self.corrector = corrector
        self.log = PosingLog()
        #: A ``reposed_keyframes`` message (its posing's first stamp, stamps in ns, poses) whose
        #: posing's ``pose_time`` has not come yet.
        self._waiting: tuple[int, np.ndarray, np.ndarray] | None = None
        #: Keyframes re-read at a corrected time offset: moved (or to be, in flight), and those
        #: integrated before and not kept, which stay where they were mapped.
        self.reposed = 0
        self.not_reposed = 0

    # --- the posing topics ----------------------------------------------------------------------------

    def on_transform(self, msg: Any) -> None:
        """``camera_from_pose_frame``: a turn (another transform than the last) re-poses what
        came before it (:meth:`_turn`) and rebuilds the map."""

        def take(message: Any) -> tuple[np.ndarray, int] | None:  # holding node._lock: one step
            turn = self.log.on_transform(message)
            return None if turn is None else (turn, self._turn(turn))

        turned = self._take(msg, take)
        if turned is None:
            return
        turn, kept = turned
        angle = float(np.degrees(rotation_angle(turn[:3, :3])))
        logger = self.node.get_logger()
        if not kept:
            logger.info(
                f'multi_view_node turned the camera {angle:.2f} deg (mount check): the keyframes from now on '
                'are mapped in it, the map so far stays as it was (no keyframes kept to re-pose)'
            )
            return
        logger.info(
            f'multi_view_node turned the camera {angle:.2f} deg (mount check): {kept} kept keyframes '
            're-posed in it, rebuilding the map'
        )
        self.corrector.start_rebuild()

    def _turn(self, turn: np.ndarray) -> int:
        """Every keyframe kept, waiting in the consistency window or last seen, posed in the
        transform before the newest, now in the newest: ``T_wc @ turn`` (those in flight: the
        log, :meth:`PosingLog.arriving`). Returns how many kept keyframes moved (holding
        node._lock)."""
        after = self.log.latest
        moved = 0
        for e in self.corrector.store.entries:
            if e.posing is not None:
                e.T_wc = e.T_wc @ turn
                e.posing = Posing(after, e.posing.offset)
                moved += 1
        self.node.move_recent(lambda stamp, T: T @ turn)
        return moved

    def on_time(self, msg: Any) -> None:
        """``pose_time``: the pose source's time images are posed at from the stamp on; it takes
        the re-read keyframes that waited for it."""

        def take(message: Any) -> tuple[int, int, int] | None:  # holding node._lock
            self.log.on_time(message)
            return self._take_reposed()

        self._after_reposed(self._take(msg, take))

    def on_reposed(self, msg: Any) -> None:
        """``reposed_keyframes``: the keyframes posed before a time offset correction, read again
        at the corrected offset. Taken once the posing it belongs to is heard (its ``pose_time``
        may come after it)."""
        node = self.node
        node.stats.received('reposed_keyframes')
        stamps, poses, bad = path_poses(msg)
        if bad:
            node.stats.dropped('bad_pose', f'reposed keyframes: {bad} of {len(msg.poses)} poses unusable')
        frame = msg.header.frame_id
        with node._lock:
            world = node._world_frame
            if frame and world and frame != world:
                node.stats.dropped('frame_mismatch', f'reposed keyframes in {frame!r}, map in {world!r}')
                return
            if not len(stamps):
                return
            if self._waiting is not None:  # its posing's pose_time never came: those keyframes stay
                node.stats.dropped(
                    'reposed_unmatched',
                    f'reposed keyframes for the posing from {messages.ns_to_sec(self._waiting[0]):.3f} s '
                    'dropped: no pose_time said that posing (the newer ones replace them)',
                )
            self._waiting = (messages.stamp_to_ns(msg.header.stamp), stamps, poses)
            moved = self._take_reposed()
        self._after_reposed(moved)

    def _take_reposed(self) -> tuple[int, int, int] | None:
        """Move the keyframes of the waiting ``reposed_keyframes`` once its posing's offset is
        known: what :meth:`_move` returns, or None (holding node._lock)."""
        if self._waiting is None:
            return None
        begins_ns, stamps, poses = self._waiting
        offset = self.log.offset_from(begins_ns)
        if offset is None:
            return None
        self._waiting = None
        # From 1 us before the first: the log's look-ups go through float seconds (ns_to_sec).
        self.log.retime(int(stamps.min()) - 1000, begins_ns, offset)
        return self._move(self.log.reread_in_latest(begins_ns, stamps, poses))

    def _move(self, reread: dict[int, np.ndarray]) -> tuple[int, int, int]:
        """Give the keyframes their re-read poses (by stamp, ns): kept, in the window, last seen;
        those after the last seen are still in flight (the log holds theirs); those before it
        were integrated and not kept (nothing to move them with). Returns ``(kept keyframes
        moved enough to rebuild, keyframes moved, integrated ones not kept)``."""
        node, corrector = self.node, self.corrector
        left = {messages.ns_to_sec(s): s for s in reread}  # the keyframes' stamps here (s) -> ns
        kept = [e for e in corrector.store.entries if e.stamp in left]
        rebuild = 0
        if kept:
            old = np.stack([e.T_wc for e in kept])
            new = np.stack([reread[left.pop(e.stamp)] for e in kept])
            metres, degrees = Corrections(new, np.ones(len(kept), bool)).moves(old)
            rebuild = int(np.sum(corrector.limits.counts(metres, degrees)))
            for e, T in zip(kept, new, strict=True):
                e.T_wc, e.posing = T, self.log.current(e.stamp)
        moved = len(kept)
        node.move_recent(lambda stamp, T: reread[left[stamp]] if stamp in left else T)
        for stamp in node.map.waiting_keys():  # the window's integrated ones are in the map already
            moved += left.pop(float(stamp), None) is not None
        last = node._last_pose[0] if node._last_pose is not None else -np.inf
        lost = sum(stamp <= last for stamp in left)
        self.log.hold({ns: reread[ns] for stamp, ns in left.items() if stamp > last})
        self.reposed += moved + len(left) - lost
        self.not_reposed += lost
        return rebuild, moved, lost

    def _after_reposed(self, moved: tuple[int, int, int] | None) -> None:
        """Say what a re-read moved (:meth:`_move`) and rebuild when a kept keyframe moved enough."""
        if moved is None:
            return
        rebuild, count, lost = moved
        node = self.node
        node.stats.published('reposings')
        limits = self.corrector.limits
        said = f'multi_view_node corrected its pose time offset: {count} keyframes here re-posed at it'
        if lost:
            said += (
                f'; {lost} integrated before and not kept (reintegration_max_mb, thinned) stay at the old '
                'offset in the map'
            )
        if not rebuild:
            node.get_logger().info(f'{said}; none kept moved enough to rebuild the map')
            return
        node.get_logger().info(
            f'{said} ({rebuild} kept ones moved by {limits.min_m:g} m or {limits.min_deg:g} deg or more), '
            'rebuilding the map'
        )
        self.corrector.start_rebuild()

    def _take(self, msg: Any, take: Callable[[Any], T]) -> T | None:
        """``take(msg)`` under the node's lock, counted; a posing that is not a rigid transform is
        dropped and counted (None). Counted once taken (or dropped), so that a count read
        elsewhere (a test, the diagnostics) never runs ahead of what the node holds."""
        node = self.node
        try:
            with node._lock:
                return take(msg)
        except ValueError as exc:
            node.stats.dropped('bad_posing', f'posing from multi_view_node unusable: {exc}')
            return None
        finally:
            node.stats.received('posing')
