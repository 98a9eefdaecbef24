"""``map_node``: fused depth + confidence + camera_info + keyframe pose -> a TSDF map.

The fused depth of a keyframe, its confidence and camera_info come from ``fusion_node`` and
the keyframe's camera-to-world pose from ``multi_view_node`` (``depth_fusion/keyframe/pose``),
each on its own topic with the keyframe's stamp, so the node pairs them by **exact stamp**
(as the fusion node pairs its inputs; the keyframe image, when it has come, colours the map).
A complete keyframe goes to the worker, which integrates it into the map (core:
``depth_fusion_ros.mapping``) once ``map.consistency_span`` later keyframes have come: only
the pixels that agree with the keyframes around them enter (mapping/consistency.py), weighted
by their confidence (and none below ``map.min_confidence``). The map in memory is bounded
(``map.max_blocks``), so memory is capped whatever the replay length; the blocks it evicts go
to a disk archive (``map.archive``) and come back when the camera does, so the saved mesh and
map file are the whole map.

Outputs: the surface as a PointCloud2 (``depth_fusion/map/points``, world frame = the pose's
frame, xyz + rgb) every ``1 / points_rate`` seconds when it changed, and the mesh as a binary
``.ply`` at ``save_path`` on the ``~/save_map`` service (std_srvs/Trigger) and, with
``save_on_shutdown``, when the node stops (what ``depth-fusion run --save-map`` uses);
``~/clear_map`` empties it. A jump in the keyframe poses (a relocalised pose source,
:mod:`..pose_jumps`) is noted, and clears the map with ``clear_on_pose_jump``. A corrected
trajectory (a loop closure, ``camera/corrected_path``) rebuilds the map from the keyframes it
kept at their corrected poses (:mod:`.map_corrections`), each keyframe compared with the
trajectory through the posing multi_view_node says it was posed with (``depth_fusion/posing/*``,
:mod:`.posing`: ``camera_from_pose_frame`` with a mount check's turn, the pose time offset);
a change of that posing moves the keyframes posed before it (:mod:`.map_posing`).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, TimeReference
from std_srvs.srv import Trigger

from ..data import messages
from ..mapping.config import ENGINES, MAP_PARAMETER_DESCRIPTIONS, MapConfig
from ..mapping.engine import make_map
from ..mapping.map_file import load_map, save_tsdf
from ..mapping.ply import write_ply
from ..mapping.surface import SurfaceMesh
from ..mapping.torch_tsdf import TorchTSDF
from ..pose_jumps import find_jump
from ..ros_home import ros_home
from .base import DepthFusionNode
from .console import run_node
from .corrected_path import TOPIC_CORRECTED_PATH
from .graph_events import GraphEvents
from .image_input import InputError, depth_from_message, pose_from_message
from .map_corrections import PARAMETERS as CORRECTION_PARAMETERS
from .map_corrections import MapCorrector
from .map_points import MapPointsPublisher
from .params import ParamSpec, build_dataclass, dataclass_specs
from .pose_jump_params import pose_jump_limits, pose_jump_parameters
from .posing import TOPIC_POSING_TIME, TOPIC_POSING_TRANSFORM, TOPIC_REPOSED_KEYFRAMES, posing_qos
from .stamp_pairing import StampPairer

NODE_NAME = 'map_node'

TOPIC_FUSED_DEPTH = 'depth_fusion/fused/depth'
TOPIC_FUSED_CONFIDENCE = 'depth_fusion/fused/confidence'
TOPIC_FUSED_CAMERA_INFO = 'depth_fusion/fused/camera_info'
TOPIC_KEYFRAME_POSE = 'depth_fusion/keyframe/pose'
TOPIC_KEYFRAME_IMAGE = 'depth_fusion/keyframe/image'
TOPIC_MAP_POINTS = 'depth_fusion/map/points'

REQUIRED_PARTS = ('depth', 'confidence', 'camera_info', 'pose')

MAP_LIMITS: dict[str, Any] = {
    'voxel_size': (1e-3, 10.0),
    'truncation': (0.0, 100.0),
    'min_depth': (0.0, None),
    'max_depth': (1e-3, None),
    'max_blocks': (1, 10_000_000),
    'block_size': (2, 32),
    'min_confidence': (0.0, 1.0),
    'confidence_power': (0.01, 8.0),
    'depth_power': (0.0, 4.0),
    'consistency_span': (0, 10),
    'consistency_tolerance': (1e-3, 0.999),
    'consistency_views': (1, 20),
    'max_weight': (1e-6, None),
    'min_weight': (0.0, None),
    'allocation_stride': (1, 64),
    'engine': ENGINES,
    'archive_max_mb': (0.0, None),
}

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec('device', 'cpu', 'torch (or Open3D) device of the TSDF: cpu, cuda, cuda:1, ...'),
    *dataclass_specs(MapConfig, 'map', MAP_PARAMETER_DESCRIPTIONS, MAP_LIMITS, skip=('device',)),
    ParamSpec(
        'points_rate',
        1.0,
        f'Hz at which the map surface is published on {TOPIC_MAP_POINTS} when it changed (0: never)',
        0.0,
        100.0,
    ),
    ParamSpec(
        'points_max', 200000, 'most points per published cloud (evenly subsampled beyond)', 1, 100_000_000
    ),
    ParamSpec('save_path', 'map.ply', 'where ~/save_map (and save_on_shutdown) write the mesh (.ply)'),
    ParamSpec(
        'save_on_shutdown', False, 'write the mesh to save_path (and the map to map_file) when the node stops'
    ),
    ParamSpec(
        'map_file',
        '',
        'the TSDF map itself (torch engine), with its archived blocks and the keyframes it keeps for a '
        'rebuild at corrected poses: loaded at start when the file exists, so a robot keeps its map across '
        "restarts; written by ~/save_map and save_on_shutdown beside the mesh ('': none)",
    ),
    ParamSpec(
        'use_color', True, f'colour the map with the keyframe image ({TOPIC_KEYFRAME_IMAGE}) when it came'
    ),
    ParamSpec(
        'pair_timeout',
        10.0,
        'seconds a keyframe waits for its missing depth, confidence, camera_info or pose (then dropped)',
        0.01,
    ),
    ParamSpec(
        'max_pending_keyframes', 16, 'keyframes waiting for their parts at most (oldest dropped)', 1, 1000
    ),
    *pose_jump_parameters('keyframe poses', 'noted, and the map cleared with clear_on_pose_jump'),
    ParamSpec(
        'clear_on_pose_jump',
        False,
        'clear the map at a pose jump: what was integrated before it is in the uncorrected world (false: '
        'keep it, a small correction leaves a slightly doubled surface; ~/clear_map clears on request)',
    ),
    *CORRECTION_PARAMETERS,
)


#: Keyframes in a row posed in another frame after which a young map follows it (:meth:`MapNode._frame_fits`).
FRAME_SWITCH_KEYFRAMES = 3


def _writable(folder: Path) -> bool:
    """Whether ``folder`` exists as a writable directory or could be made (its nearest existing
    ancestor is a writable directory)."""
    for candidate in (folder, *folder.parents):
        if candidate.exists():
            return candidate.is_dir() and os.access(candidate, os.W_OK | os.X_OK)
    return False


def default_archive_dir() -> Path:
    """Where map_node's archive goes unless ``map.archive_dir`` says: under ``$ROS_HOME``
    (``~/.ros``, where ROS keeps its logs: a disk), not the temporary directory, which some
    systems keep in memory (tmpfs) and which would then hold what ``max_blocks`` keeps out of it."""
    return ros_home() / 'depth_fusion_ros' / 'map_archive'


class MapNode(DepthFusionNode):
    """Pairs fused keyframes with their poses by stamp and integrates them into a TSDF."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, PARAMETERS, **kwargs)
        self.events = GraphEvents(self)  # the ready line a graph runner waits for
        p = self.params
        try:
            config = build_dataclass(MapConfig, p, 'map', device=str(p['device'])).validate()
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        config.archive_dir = config.archive_dir or str(default_archive_dir())
        save_path = Path(str(p['save_path']))
        if save_path.suffix.lower() != '.ply':
            raise ValueError(f'{self.get_name()}: parameter save_path={str(save_path)!r} must end in .ply')
        try:
            self.map, engine_note = make_map(config)
        except ValueError as exc:  # a device this machine lacks
            raise ValueError(f'{self.get_name()}: {exc}') from None
        self.get_logger().info(engine_note)
        try:
            self.corrector = MapCorrector(self)
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        self.map.on_integrated = self.corrector.keep
        self._lock = threading.Lock()
        self._dirty = False
        self._world_frame = ''
        #: another frame keyframes came in, and how many in a row (:meth:`_frame_fits`)
        self._other_frame = ('', 0)
        self._loaded = False
        self.map_file = Path(str(p['map_file'])) if str(p['map_file']) else None
        self._load_map_file()
        self._integrated = 0
        self.jump_limits = pose_jump_limits(p)
        #: Stamp (s) and pose of the last keyframe integrated, for the pose-jump test.
        self._last_pose: tuple[float, np.ndarray] | None = None
        required = REQUIRED_PARTS
        optional = ('rgb',) if p['use_color'] else ()
        self.pairer = StampPairer(
            required,
            optional,
            timeout=float(p['pair_timeout']),
            max_pending=int(p['max_pending_keyframes']),
            on_complete=lambda pairing: self.worker.submit(pairing),
            on_drop=self.stats.dropped,
            restart_after=float(p['stream_restart_jump']),
            on_restart=lambda part, stamp_ns: self.note_stream_restart(
                part,
                stamp_ns,
                'integrated into the same map (for another scene, save it and start map_node again)',
            ),
        )
        self._points_pub = self.create_publisher(PointCloud2, TOPIC_MAP_POINTS, self.output_qos)
        self.worker = self.make_worker('map', self._integrate)
        q = self.input_qos
        self.subscribe(Image, TOPIC_FUSED_DEPTH, lambda m: self._on_image(m, 'depth'), q)
        self.subscribe(Image, TOPIC_FUSED_CONFIDENCE, lambda m: self._on_image(m, 'confidence'), q)
        self.subscribe(CameraInfo, TOPIC_FUSED_CAMERA_INFO, self._on_camera_info, q)
        self.subscribe(PoseStamped, TOPIC_KEYFRAME_POSE, self._on_pose, q)
        if p['use_color']:
            self.subscribe(Image, TOPIC_KEYFRAME_IMAGE, self._on_keyframe_image, q)
        self.subscribe(PathMsg, TOPIC_CORRECTED_PATH, self.corrector.on_path, q)
        latched = posing_qos()
        posing = self.corrector.posing
        self.subscribe(TransformStamped, TOPIC_POSING_TRANSFORM, posing.on_transform, latched)
        self.subscribe(TimeReference, TOPIC_POSING_TIME, posing.on_time, latched)
        self.subscribe(PathMsg, TOPIC_REPOSED_KEYFRAMES, posing.on_reposed, latched)
        self.create_service(Trigger, '~/save_map', self._on_save)
        self.create_service(Trigger, '~/clear_map', self._on_clear)
        self.create_wall_timer(min(0.5, float(p['pair_timeout']) / 2), self._expire)
        self.points = MapPointsPublisher(
            self, self._points_pub, float(p['points_rate']), int(p['points_max'])
        )
        if float(p['points_rate']) > 0:
            self.create_wall_timer(1.0 / float(p['points_rate']), self.points.tick)
        self.events.ready()
        cap = config.max_blocks * config.bytes_per_block / 2**20
        self.get_logger().info(
            f'map: {config.voxel_size * 100:g} cm voxels, truncation {config.truncation_m * 100:g} cm, '
            f'depth {config.min_depth:g}-{config.max_depth:g} m, at most {config.max_blocks} blocks '
            f'({cap:.0f} MiB) in memory, {self._archive_note(config)}; '
            f'{self.resolve_topic_name(TOPIC_FUSED_DEPTH)} + '
            f'{self.resolve_topic_name(TOPIC_KEYFRAME_POSE)} -> {self.resolve_topic_name(TOPIC_MAP_POINTS)}, '
            f'mesh on {self.resolve_service_name("~/save_map")}; corrected trajectories on '
            f'{self.resolve_topic_name(TOPIC_CORRECTED_PATH)} rebuild it from the keyframes '
            f'kept (at most {self.corrector.store.max_bytes / 2**20:g} MiB, thinned with age)'
        )

    def _archive_note(self, config: MapConfig) -> str:
        if self.map.archive is None:
            return 'the blocks evicted beyond them dropped (map.archive off or not this engine)'
        if not _writable(Path(config.archive_dir)):
            self.get_logger().warning(
                f'map.archive_dir {config.archive_dir} cannot be written: blocks evicted beyond '
                f'map.max_blocks={config.max_blocks} will be lost (counted as blocks_lost)'
            )
        return (
            f'the blocks evicted beyond them archived in {config.archive_dir} '
            f'(up to {config.archive_max_mb:g} MiB)'
        )

    # --- callbacks: collect parts by stamp ------------------------------------------------------------

    def _on_image(self, msg: Image, part: str) -> None:
        self.stats.received(part)
        try:
            value = depth_from_message(msg, f'fused {part}')
        except InputError as exc:
            self.stats.dropped(exc.reason, str(exc))
            return
        self.pairer.add(msg.header, part, value)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.stats.received('camera_info')
        try:
            calib = messages.camera_info_to_calibration(msg)
        except ValueError as exc:
            self.stats.dropped('bad_camera_info', f'fused camera_info: {exc}')
            return
        if calib.is_distorted:
            self.stats.dropped(
                'bad_camera_info', 'fused camera_info has distortion: expected the working grid'
            )
            return
        self.pairer.add(msg.header, 'camera_info', calib.camera)

    def _on_pose(self, msg: PoseStamped) -> None:
        self.stats.received('pose')
        try:
            T_wc = pose_from_message(msg)
        except InputError as exc:
            self.stats.dropped(exc.reason, str(exc))
            return
        self.pairer.add(msg.header, 'pose', (T_wc, msg.header.frame_id))

    def _on_keyframe_image(self, msg: Image) -> None:
        try:
            rgb = messages.image_to_rgb(msg)
        except ValueError as exc:
            self.stats.dropped('bad_encoding', f'keyframe image: {exc}')
            return
        self.pairer.add(msg.header, 'rgb', rgb)

    def _expire(self) -> None:
        self.pairer.expire(time.monotonic())

    # --- worker ---------------------------------------------------------------------------------------

    def _integrate(self, pairing: Any) -> None:
        parts = pairing.parts
        camera = parts['camera_info']
        depth, confidence = parts['depth'], parts['confidence']
        T_wc, frame_id = parts['pose']
        stamp = messages.ns_to_sec(pairing.stamp_ns)
        shape = (camera.height, camera.width)
        if depth.shape != shape or confidence.shape != shape:
            self.stats.dropped(
                'size_mismatch',
                f'keyframe {stamp:.3f}: depth {depth.shape}, confidence {confidence.shape}, '
                f'camera_info {shape}',
            )
            return
        rgb = parts.get('rgb')
        if rgb is not None and rgb.shape[:2] != shape:
            rgb = None
        with self._lock:
            if not self._frame_fits(frame_id, stamp):
                return
            T_wc = self.corrector.posings.arriving(pairing.stamp_ns, T_wc)  # posed before a posing change
            self._check_pose_jump(stamp, T_wc)  # (a clear there forgets the frame: this one sets it)
            self._world_frame = self._world_frame or frame_id or 'world'
            self.corrector.note_segment(stamp)
            before = (self.map.evicted_blocks, self.map.lost_blocks, self.map.skipped_blocks)
            self.map.integrate(depth, T_wc, camera, confidence=confidence, rgb=rgb, key=stamp)
            self._note_evictions(*before)
            self._dirty = True
            self._integrated += 1
        self.stats.published('integrated')
        self.stats.processed(time.monotonic() - pairing.first_seen)

    def _frame_fits(self, frame_id: str, stamp: float) -> bool:
        """Whether a keyframe posed in ``frame_id`` goes into this map (holding ``_lock``).

        One map is in one world frame, set by its first keyframe; a keyframe posed in another
        is dropped (``frame_mismatch``). Why a young map follows instead: its frame was set by
        its first keyframe alone, and one stray pose (another node's frame, a SLAM that
        restarted under another name) would otherwise lock the map out of the pose source's
        real frame for good. So a map of fewer than :data:`FRAME_SWITCH_KEYFRAMES` keyframes,
        none loaded from ``map_file``, starts over in the other frame once that many keyframes in
        a row are posed in it (noted ``world_frame_changed``). An established or loaded map is
        never cleared for it: its keyframes stay dropped, and ~/clear_map starts a new map."""
        if not self._world_frame or not frame_id or frame_id == self._world_frame:
            self._other_frame = ('', 0)
            return True
        name, count = self._other_frame
        count = count + 1 if name == frame_id else 1
        self._other_frame = (frame_id, count)
        young = self._integrated < FRAME_SWITCH_KEYFRAMES and not self._loaded
        if young and count >= FRAME_SWITCH_KEYFRAMES:
            old, dropped = self._world_frame, self._clear()
            self.stats.noted(
                'world_frame_changed',
                f'{count} keyframes in a row posed in {frame_id!r}, the map of {dropped} keyframes in '
                f'{old!r}: the map starts over in {frame_id!r}',
            )
            self._other_frame = ('', 0)
            return True
        what = (
            f'it follows after {FRAME_SWITCH_KEYFRAMES} in a row'
            if young
            else '~/clear_map starts a map in the new frame'
        )
        self.stats.dropped(
            'frame_mismatch',
            f'keyframe {stamp:.3f}: pose in {frame_id!r}, map in {self._world_frame!r} ({what})',
        )
        return False

    def _note_evictions(self, evicted: int, lost: int, skipped: int) -> None:
        """Say when the map evicted blocks (to the archive) and when some were lost (no archive,
        the archive full or refused by the disk). Called holding ``_lock``."""
        if self.map.evicted_blocks > evicted:
            archive = self.map.archive
            where = f'to the archive {archive.path}' if archive is not None else 'dropped (map.archive off)'
            self.stats.noted(
                'blocks_evicted',
                f'map full ({self.map.config.max_blocks} blocks): the farthest moved {where}'
                + (
                    f'; {TOPIC_MAP_POINTS}, ~/save_map and map_file keep the whole map'
                    if archive is not None
                    else ''
                ),
            )
        over = self.map.skipped_blocks - skipped
        if over > 0:
            self.stats.noted(
                'keyframe_larger_than_map',
                f'a keyframe needed {over} blocks more than map.max_blocks={self.map.config.max_blocks} '
                'holds: its depth there was left out (raise map.max_blocks)',
            )
        gone = self.map.lost_blocks - lost
        if gone > 0:
            self.stats.dropped(
                'blocks_lost', f'{gone} evicted map blocks lost (see the map archive line above)', count=gone
            )

    def _load_map_file(self) -> None:
        """The map saved by an earlier run (``map_file``), when there is one: integration goes on
        into it. A file that is not such a map, or does not fit the configuration, stops the
        node with one line naming it (a robot told to keep its map must not start a new one)."""
        if self.map_file is None:
            return
        if not isinstance(self.map.engine, TorchTSDF):
            raise ValueError(f'{self.get_name()}: map_file needs the torch engine (map.engine: torch)')
        if not self.map_file.exists():
            self.get_logger().info(f'map_file {self.map_file} does not exist yet: starting an empty map')
            return
        try:
            loaded = load_map(self.map.engine, self.map_file, self.corrector.store)
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        self._world_frame = loaded.world_frame
        self._loaded = True
        self.corrector.base = loaded.base
        self._dirty = True
        frame = self._world_frame or '?'
        archived = self.map.engine.archived_blocks
        movable = (
            f'{loaded.keyframes} kept keyframes restored: a corrected trajectory rebuilds it'
            + (' (with the part mapped before them fixed)' if loaded.base is not None else '')
            if loaded.keyframes
            else 'no kept keyframes in it: a corrected trajectory cannot move it'
        )
        self.get_logger().info(
            f'map loaded from {self.map_file}: {self.map.n_blocks} blocks in frame {frame!r}'
            + (f', {archived} more archived (beyond map.max_blocks)' if archived else '')
            + f'; {movable}'
        )

    def move_recent(self, pose_of: Callable[[float, np.ndarray], np.ndarray]) -> None:
        """Give the keyframes not yet kept their new poses, ``pose_of(stamp, T_wc)``: those in the
        consistency test's window and the pose-jump test's last pose (a loop closure, a mount
        turn or a time offset correction moved them; holding ``_lock``)."""
        self.map.move_window(lambda key, T: pose_of(float(key), T))
        if self._last_pose is not None:
            stamp, T = self._last_pose
            self._last_pose = (stamp, pose_of(float(stamp), T))

    def _check_pose_jump(self, stamp: float, T_wc: np.ndarray) -> None:
        """Note a pose jump since the last keyframe integrated (``pose_jump``), and clear the
        map there with ``clear_on_pose_jump``. Called holding ``_lock``."""
        last, self._last_pose = self._last_pose, (stamp, T_wc)
        if last is None or stamp <= last[0]:
            return
        jump = find_jump(self.jump_limits, last[0], last[1], stamp, T_wc)
        if jump is None:
            return
        self.corrector.store.new_segment()  # a corrected trajectory never interpolates across it
        clear = bool(self.params['clear_on_pose_jump'])
        what = (
            f'map cleared ({self._integrated} keyframes)'
            if clear
            else 'the map before it stays in the uncorrected world (~/clear_map, or clear_on_pose_jump)'
        )
        self.stats.noted(
            'pose_jump',
            f'keyframe pose jumped {jump.describe(self.jump_limits)} at {stamp:.3f} s (the pose source '
            f'relocalised?): {what}',
        )
        if clear:
            self._clear()

    def _clear(self) -> int:
        """Start an empty map with the same settings (holding ``_lock``); returns the keyframes dropped."""
        dropped = self._integrated
        self.map.close()  # its archive goes with it
        self.map, _ = make_map(self.map.config)
        self.map.on_integrated = self.corrector.keep
        self.corrector.clear()
        self.corrector.base = None
        self._integrated = 0
        self._world_frame = ''  # the next keyframe's frame: a cleared map may start in another
        self._loaded = False
        self._dirty = True
        return dropped

    def clear_map(self) -> int:
        """Empty the map (thread-safe); returns how many keyframes it held."""
        with self._lock:
            return self._clear()

    def _on_clear(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        dropped = self.clear_map()
        response.success = True
        response.message = f'map cleared: {dropped} keyframes dropped'
        self.get_logger().info(f'clear_map: {response.message}')
        return response

    # --- outputs --------------------------------------------------------------------------------------

    def diagnostic_extra(self) -> dict[str, Any]:
        """The map's size against its cap on ``/diagnostics``: a robot can watch it stay bounded."""
        config = self.map.config
        return {
            'keyframes integrated': self._integrated - self.map.pending,
            'keyframes waiting for the consistency test': self.map.pending,
            'pixels left out by the consistency test': self.map.pixels_rejected,
            'blocks': self.map.n_blocks,
            'blocks evicted': self.map.evicted_blocks,
            'blocks archived on disk': self.map.archived_blocks,
            'blocks restored from the archive': self.map.restored_blocks,
            'blocks lost': self.map.lost_blocks,
            'blocks keyframes needed beyond the cap': self.map.skipped_blocks,
            'voxel storage MiB': round(self.map.memory_bytes / 2**20, 2),
            'cap MiB': round(config.max_blocks * config.bytes_per_block / 2**20, 2),
            'surface extraction s': round(self.points.last_seconds, 3),
            'archived blocks in the published cloud': len(self.points.archived.blocks),
            **self.corrector.diagnostics(),
        }

    @property
    def integrated(self) -> int:
        """Keyframes taken into the map so far (the last ``map.consistency_span`` of them wait
        for their successors before they are integrated)."""
        return self._integrated

    def extract(self, flush: bool = False) -> tuple[SurfaceMesh, str]:
        """The current mesh and the world frame it is in (thread-safe). ``flush``: integrate
        the keyframes still waiting for the consistency test's successors first (for a saved
        mesh; the published points just lag ``map.consistency_span`` keyframes)."""
        with self._lock:
            if flush:
                self.map.flush()
            return self.map.mesh(), self._world_frame or 'world'

    def save_map(self, path: str | Path | None = None) -> tuple[Path, int, int]:
        """Write the mesh to ``path`` (default ``save_path``): (path, vertices, triangles).

        ``ValueError`` when the map is still empty: an empty file would look like a map.
        """
        path = Path(path or str(self.params['save_path']))
        mesh, _ = self.extract(flush=True)
        if mesh.is_empty:
            raise ValueError(
                f'the map is empty ({self._integrated} keyframes taken, {self.map.pixels_rejected} pixels '
                f'left out by the consistency test): nothing written to {path}'
            )
        write_ply(path, mesh)
        if self.map_file is not None:
            with self._lock:
                save_tsdf(
                    self.map.engine,
                    self.map_file,
                    self._world_frame,
                    self.corrector.store,
                    self.corrector.base,
                )
        return path, len(mesh.vertices), len(mesh.triangles)

    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            path, nv, nt = self.save_map()
        except (OSError, ValueError) as exc:
            response.success, response.message = False, str(exc)
            self.get_logger().warning(f'save_map: {exc}')
            return response
        response.success = True
        response.message = f'{path}: {nv} vertices, {nt} triangles from {self._integrated} keyframes'
        if self.map_file is not None:
            response.message += f'; map written to {self.map_file}'
        self.get_logger().info(f'save_map: {response.message}')
        return response

    def destroy_node(self) -> None:
        """Finish the integrations in hand, then write the mesh if ``save_on_shutdown``."""
        if not self._destroyed:
            self.points.wait(10.0)  # a publication in flight finishes before the node goes
        if not self._destroyed and self.params['save_on_shutdown']:
            self.wait_idle(10.0)
            if not self.corrector.wait(60.0):
                self.get_logger().warning('map rebuild still running after 60 s: saving the map as it was')
            try:
                path, nv, nt = self.save_map()
                self.get_logger().info(f'map saved to {path} ({nv} vertices, {nt} triangles)')
            except (OSError, ValueError) as exc:
                self.get_logger().error(f'map not saved: {exc}')
        closing = not self._destroyed
        super().destroy_node()  # the worker stops first: nothing integrates into a closed archive
        if closing:
            with self._lock:
                self.map.close()  # the archive's file goes with the node


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point: ``map_node --ros-args --params-file config/depth_fusion.yaml``."""
    return run_node(MapNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
