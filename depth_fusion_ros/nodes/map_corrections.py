"""map_node's loop-closure handling: a corrected trajectory moves the keyframes, and the map
is rebuilt from them at their corrected poses, in the background.

A SLAM that closes a loop publishes its corrected trajectory; here as ``nav_msgs/Path``
(``camera/corrected_path``: one PoseStamped per pose, stamped, in the world frame of the
keyframe poses; remap it to the SLAM's topic). The core (mapping/keyframe_store.py,
pose_corrections.py) works out each kept keyframe's corrected pose; when one moved by
at least ``correction_min_translation`` / ``correction_min_rotation_deg``, a thread integrates
every kept keyframe again into a fresh engine, integrates the keyframes that came meanwhile,
and swaps the map under the node's lock. Integration never waits for a rebuild, and the old
map is served until the new one is whole.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from ..geometry import transform_from_parameter
from ..malloc_tuning import release_free_memory
from ..mapping.engine import make_engine
from ..mapping.keyframe_store import KeyframeStore, PendingKeyframe, rebuild
from ..pose_corrections import Posing
from .corrected_path import (
    TOPIC_CORRECTED_PATH,
    camera_from_pose_frame_parameter,
    correction_limits,
    correction_parameters,
    pose_inverted_parameter,
    read_path,
)
from .map_posing import MapPosing
from .params import ParamSpec

if TYPE_CHECKING:
    from .map_node import MapNode

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'reintegration_max_mb',
        128.0,
        'MiB of keyframes kept (half resolution: 115 KB each at 320x240, ~1100 in 128 MiB; beyond, every '
        'second keyframe of the older half is dropped) to rebuild the map at the corrected poses of a '
        f'trajectory on {TOPIC_CORRECTED_PATH} (0: none kept, corrections ignored)',
        0.0,
        1e6,
    ),
    *correction_parameters('rebuilds the map there'),
    camera_from_pose_frame_parameter(),
    pose_inverted_parameter(),
)


class MapCorrector:
    """The kept keyframes of a :class:`MapNode`, their corrections and the background rebuild."""

    def __init__(self, node: MapNode) -> None:
        self.node = node
        p = node.params
        self.store = KeyframeStore(int(float(p['reintegration_max_mb']) * 2**20))
        self.limits = correction_limits(p)
        self.T_pose_cam = transform_from_parameter(p['camera_from_pose_frame'])
        #: How multi_view_node posed each keyframe (nodes/posing.py, nodes/map_posing.py); this
        #: node's own ``camera_from_pose_frame`` for keyframes it said nothing about.
        self.posing = MapPosing(node, self)
        self.posings = self.posing.log
        self.default_posing = Posing(self.T_pose_cam, 0.0)
        self.rebuilds = 0
        self.last_rebuild_s = 0.0
        self._thread: threading.Thread | None = None
        self._again = False
        self._generation = 0  # bumped when the map is cleared: a rebuild from before is not swapped in
        #: The store's segment of each keyframe in the consistency test's window (by stamp).
        self._segments: dict[float, int] = {}
        self._last_key: float | None = None
        #: A map loaded from ``map_file`` (its blocks): a rebuild starts from it, since its
        #: keyframes are not kept (it cannot be moved, only added to).
        self.base: Any = None
        self._state = threading.Lock()  # guards _thread and _again (node._lock guards the map and store)

    # --- called holding node._lock ---------------------------------------------------------------------

    def keep(
        self, key: object, depth: np.ndarray, T_wc: np.ndarray, camera: Any, confidence: Any, rgb: Any
    ) -> None:
        """``ConsistentMap.on_integrated``: keep the keyframe as it went into the engine, in the
        segment it entered the window in."""
        segment = self._segments.get(float(key), self.store.segment)
        thinned = self.store.thinned
        posing = self.posings.current(float(key))
        self.store.add(float(key), depth, T_wc, camera, confidence, rgb, segment=segment, posing=posing)
        if self.store.thinned > thinned:
            # The dropped keyframes' own mappings went back with them (keyframe_store.own_pages);
            # the heap's share (their small objects, and keyframes past MAX_MAPPED_ENTRIES) would
            # stay under malloc_tuning.py's raised trim threshold: hand it back too.
            release_free_memory()

    # --- the corrected trajectory ----------------------------------------------------------------------

    def on_path(self, msg: Any) -> None:
        """A corrected trajectory: move the kept (and waiting) keyframes, then rebuild if one moved."""
        node = self.node
        with node._lock:
            # The pose source's own poses: each keyframe is compared through its own posing.
            inverted = bool(node.params['pose_inverted'])
            path = read_path(node.stats, msg, np.eye(4), node._world_frame, inverted)
            if path is None:
                return
            if self.store.max_bytes <= 0:
                node.stats.dropped(
                    'corrections_off',
                    'corrected trajectory ignored: reintegration_max_mb is 0 (nothing kept)',
                )
                return
            stamps, poses = path
            pending = self._pending()
            summary = self.store.correct(stamps, poses, self.limits, self.default_posing, pending)
            self._move_pending(pending, summary.others)
        node.stats.published('corrections')
        if summary.moved == 0:  # a pose source that republishes its trajectory: not worth a line each time
            node.get_logger().debug(
                f'corrected trajectory ({len(stamps)} poses): {summary.corrected} kept keyframes covered, '
                f'none moved by {self.limits.min_m:g} m or {self.limits.min_deg:g} deg: map kept as it is'
            )
            return
        node.get_logger().info(
            f'corrected trajectory ({len(stamps)} poses) moved {summary.moved} of {len(self.store.entries)} '
            f'kept keyframes (largest {summary.largest_m:.3f} m, {summary.largest_deg:.2f} deg): '
            'rebuilding the map'
        )
        self.start_rebuild()

    def note_segment(self, key: float) -> None:
        """The keyframe ``key`` enters the consistency test's window in the store's current
        segment, or a new one when its stamp goes back (a restarted stream; a pose jump started
        one already). Called after the pose-jump test, holding node._lock."""
        key = float(key)
        if self._last_key is not None and key <= self._last_key:
            self.store.new_segment()
        self._last_key = key
        self._segments[key] = self.store.segment
        window = {float(k) for k, _ in self.node.map.window_keyframes()} | {key}
        for gone in [k for k in self._segments if k not in window]:
            del self._segments[gone]

    def _pending(self) -> list[PendingKeyframe]:
        """The keyframes in the consistency test's window, then the pose-jump test's last pose:
        they move with the kept ones, corrected together (holding node._lock)."""
        node = self.node
        keyframes = [
            (float(k), T, self._segments.get(float(k), self.store.segment))
            for k, T in node.map.window_keyframes()
        ]
        if node._last_pose is not None:
            keyframes.append((float(node._last_pose[0]), node._last_pose[1], self.store.segment))
        return [PendingKeyframe(t, T, segment, self.posings.current(t)) for t, T, segment in keyframes]

    def _move_pending(self, pending: list[PendingKeyframe], moved: np.ndarray | None) -> None:
        """Give :meth:`_pending`'s keyframes their corrected poses (holding node._lock)."""
        if moved is None:
            return
        node = self.node
        now = {p.stamp: T for p, T in zip(pending, moved, strict=True)}
        node.move_recent(lambda stamp, T: now.get(stamp, T))

    # --- the rebuild thread ----------------------------------------------------------------------------

    def start_rebuild(self) -> None:
        with self._state:
            if self._thread is not None and self._thread.is_alive():
                self._again = True  # the running rebuild is already out of date: once more after it
                return
            self._thread = threading.Thread(target=self._rebuild_loop, name='map_rebuild', daemon=True)
            self._thread.start()

    def _rebuild_loop(self) -> None:
        while True:
            try:
                self._rebuild_once()
            except Exception as exc:  # a failed rebuild keeps the old map; the node goes on
                self.node.stats.dropped('rebuild_failed', f'map rebuild failed: {type(exc).__name__}: {exc}')
            with self._state:
                if not self._again:
                    self._thread = None
                    return
                self._again = False

    def _rebuild_once(self) -> None:
        node = self.node
        t0 = time.monotonic()
        with node._lock:
            entries = list(self.store.entries)
            last = self.store.last_seq
            config = node.map.config
            generation = self._generation
            base = self.base
            centre = node.map.camera_position
        engine, _ = make_engine(config)
        if base is not None:  # more than max_blocks: the rest to the new engine's archive
            engine.load_blocks(base.coords, base.tsdf, base.weight, base.colour, centre=centre)
        rebuild(engine, entries)  # the long part, outside the lock: integration goes on meanwhile
        with node._lock:
            if generation != self._generation:
                node.get_logger().info('map rebuild dropped: the map was cleared while it ran')
                engine.close()
                return
            late = rebuild(engine, self.store.newer_than(last))
            old, node.map.engine = node.map.engine, engine
            old.close()  # its archive: blocks at the uncorrected poses
            kept = len(self.store.entries)
            node._integrated = kept + node.map.pending
            node._dirty = True
        self.rebuilds += 1
        self.last_rebuild_s = time.monotonic() - t0
        thinned = self.store.thinned
        older = f'; {thinned} older keyframes thinned out of the store are no longer in it' if thinned else ''
        node.get_logger().info(
            f'map rebuilt at the corrected poses from {kept} keyframes ({late} came during it) in '
            f'{self.last_rebuild_s:.1f} s{older}'
        )
        node.stats.published('rebuilds')

    def busy(self) -> bool:
        with self._state:
            return self._thread is not None and self._thread.is_alive()

    def wait(self, timeout: float) -> bool:
        """Wait for a running rebuild (shutdown, tests); True when none is running."""
        deadline = time.monotonic() + timeout
        while self.busy() and time.monotonic() < deadline:
            time.sleep(0.02)
        return not self.busy()

    def clear(self) -> None:
        """The map was cleared: keep nothing from before (holding node._lock)."""
        self.store.clear()
        self._generation += 1

    def diagnostics(self) -> dict[str, Any]:
        return {
            'keyframes kept for a rebuild': len(self.store.entries),
            'kept keyframes MiB': round(self.store.memory_bytes / 2**20, 2),
            'keyframes thinned out of the store': self.store.thinned,
            'rebuilds at corrected poses': self.rebuilds,
            'keyframes re-read at a corrected time offset': self.posing.reposed,
            'keyframes integrated and not kept at a time offset correction': self.posing.not_reposed,
        }
