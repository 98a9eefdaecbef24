"""Write rosbag2 recordings (mcap or sqlite3) from TUM folders and ROS 1 bags, with rosbags.

The output is raw sensor data in the layout every node and ``load_bag_sequence`` expect
(docs/data.md), all stamped with the colour image's stamp (header stamp = bag timestamp):

==========================  ==============================  =================================
topic (default)             type                            content
==========================  ==============================  =================================
/camera/rgb/image_color     sensor_msgs/Image rgb8          original colour, NOT undistorted
/camera/rgb/camera_info     sensor_msgs/CameraInfo          K and D, one per colour frame
/camera/depth/image         sensor_msgs/Image 32FC1         ground-truth depth (m, NaN none)
/camera/pose                geometry_msgs/PoseStamped       camera-to-world, frame ``world``
==========================  ==============================  =================================

A conversion writes into a hidden temporary folder next to the target and renames it into
place only when it completes, so an interrupted run never leaves a bag that looks complete.
"""

from __future__ import annotations

import heapq
import logging
import shutil
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

from ..progress import progress
from .compressed import RAW_COLOUR, ColourFormat
from .messages import (
    camera_info_msg,
    camera_info_to_calibration,
    depth_image_msg,
    header_msg,
    image_to_depth,
    image_to_rgb,
    pose_stamped_msg,
    pose_stamped_to_matrix,
    stamp_to_ns,
    transform_to_matrix,
)
from .rosbag_read import bag_typestore
from .tum import (
    AssociatedFrame,
    TumTrajectory,
    associate,
    nearest_stamps,
    read_camera_yaml,
    read_depth_file,
    read_groundtruth,
    read_rgb_file,
    read_tum_index,
)
from .undistort import CameraCalibration

logger = logging.getLogger(__name__)

T = TypeVar('T')
R = TypeVar('R')

NS_PER_SEC = 1_000_000_000
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TF_TOPICS = ('/tf', '/tf_static')


@dataclass(frozen=True)
class BagTopics:
    """Topic names of a converted bag (and, for ROS 1 sources, of the source bag)."""

    rgb: str = '/camera/rgb/image_color'
    camera_info: str = '/camera/rgb/camera_info'
    depth: str = '/camera/depth/image'
    pose: str = '/camera/pose'


@dataclass(frozen=True)
class FrameIds:
    """``header.frame_id`` of the camera topics and of the poses."""

    camera: str = 'camera_rgb_optical_frame'
    world: str = 'world'


@dataclass
class ConvertResult:
    """What a conversion wrote."""

    path: Path
    frames: int
    messages: dict[str, int]
    dropped: dict[str, int] = field(default_factory=dict)
    pose_source: str = 'groundtruth'
    seconds: float = 0.0


# --------------------------------------------------------------------------- output


def _is_rosbag2(path: Path) -> bool:
    return path.is_dir() and (path / 'metadata.yaml').is_file()


class AtomicBagWriter:
    """A rosbag2 writer that only makes ``out`` appear once everything is written.

    The bag is written to ``<parent>/.<name>.<random>.partial/<name>`` and moved to ``out`` on
    a clean exit; on an exception (or Ctrl-C) the partial folder is removed. An existing
    ``out`` is an error unless ``overwrite`` (and then only a rosbag2 folder is replaced).
    """

    def __init__(self, out: str | Path, storage: str = 'mcap', overwrite: bool = False) -> None:
        if storage not in STORAGES:
            raise ValueError(f'storage must be one of {", ".join(STORAGES)}, got {storage!r}')
        self.out = Path(out)
        if self.out.exists() or self.out.is_symlink():
            if not overwrite:
                raise ValueError(f'{self.out} already exists (pass --overwrite to replace it)')
            if not _is_rosbag2(self.out):
                raise ValueError(f'{self.out} exists and is not a rosbag2 folder: refusing to overwrite it')
        self.storage = storage
        self.typestore = bag_typestore()
        self.counts: dict[str, int] = {}
        self._connections: dict[str, Any] = {}
        self._tmp_root: Path | None = None
        self._writer: Writer | None = None

    def __enter__(self) -> AtomicBagWriter:
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self._tmp_root = Path(
            tempfile.mkdtemp(prefix=f'.{self.out.name}.', suffix='.partial', dir=self.out.parent)
        )
        try:
            self._writer = Writer(
                self._tmp_root / self.out.name, version=9, storage_plugin=STORAGES[self.storage]
            )
            self._writer.open()
        except BaseException:
            shutil.rmtree(self._tmp_root, ignore_errors=True)
            raise
        return self

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Serialise ``msg`` (a rosbags message) and write it at ``stamp_ns``."""
        self.write_raw(topic, msgtype, stamp_ns, self.typestore.serialize_cdr(msg, msgtype))

    def write_raw(self, topic: str, msgtype: str, stamp_ns: int, data: bytes | memoryview) -> None:
        assert self._writer is not None, 'use AtomicBagWriter as a context manager'
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise ValueError(f'topic {topic} already holds {conn.msgtype}, cannot write {msgtype}')
        self._writer.write(conn, int(stamp_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        assert self._writer is not None and self._tmp_root is not None
        try:
            self._writer.close()
            if exc_type is None:
                self._publish()
        finally:
            shutil.rmtree(self._tmp_root, ignore_errors=True)

    def _publish(self) -> None:
        """Move the finished bag into place (an old bag is moved aside first, then deleted)."""
        assert self._tmp_root is not None
        if self.out.exists():
            self.out.rename(self._tmp_root / 'replaced')
        (self._tmp_root / self.out.name).rename(self.out)


def _prefetch(fn: Callable[[T], R], items: Iterable[T], depth: int = 4) -> Iterator[R]:
    """``map(fn, items)`` computed ``depth`` items ahead on threads (bounded memory, in order).

    Image decoding releases the GIL, so reading the next frames overlaps serialising this one.
    """
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending: deque[Future[R]] = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) > depth:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


# --------------------------------------------------------------------------- TUM folder


def tum_to_rosbag(
    src: str | Path,
    out: str | Path,
    *,
    storage: str = 'mcap',
    max_frames: int | None = None,
    topics: BagTopics = BagTopics(),
    frame_ids: FrameIds = FrameIds(),
    depth_max_gap: float = 0.02,
    include_depth: bool = True,
    overwrite: bool = False,
    show_progress: bool = True,
    colour: ColourFormat = RAW_COLOUR,
) -> ConvertResult:
    """Convert a TUM folder (with camera.yaml and groundtruth.txt) into a rosbag2.

    ``colour`` chooses raw rgb8 images or CompressedImage (PNG/JPEG) on ``<rgb>/compressed``.

    Colour frames outside the ground truth (and, with ``include_depth``, without a depth image
    within ``depth_max_gap`` s) are not written; ``ConvertResult.dropped`` counts them.
    """
    start = time.perf_counter()
    index = read_tum_index(src, require_depth=include_depth)
    assoc = associate(
        index, depth_max_gap, require_depth=include_depth, require_pose=True, max_frames=max_frames
    )
    if not assoc.frames:
        raise ValueError(f'{src}: no frame to write (dropped: {assoc.dropped})')
    calib = index.calibration
    camera = calib.camera

    def decode(af: AssociatedFrame) -> tuple[AssociatedFrame, np.ndarray, np.ndarray | None]:
        rgb = read_rgb_file(af.rgb_file, camera)
        depth = read_depth_file(af.depth_file, camera) if include_depth else None
        return af, rgb, depth

    writer = AtomicBagWriter(out, storage, overwrite)
    ts = writer.typestore
    with writer:
        frames = progress(assoc.frames, desc='convert', unit='frame', disable=not show_progress)
        for af, rgb, depth in _prefetch(decode, frames):
            stamp = af.stamp_ns
            hdr = header_msg(stamp, frame_ids.camera, kind=ts)
            rgb_topic, rgb_type, rgb_msg = colour.message(rgb, hdr, topics.rgb, kind=ts)
            writer.write(rgb_topic, rgb_type, stamp, rgb_msg)
            writer.write(topics.camera_info, CAMERA_INFO, stamp, camera_info_msg(calib, hdr, kind=ts))
            if depth is not None:
                writer.write(topics.depth, IMAGE, stamp, depth_image_msg(depth, hdr, kind=ts))
            pose_hdr = header_msg(stamp, frame_ids.world, kind=ts)
            writer.write(topics.pose, POSE_STAMPED, stamp, pose_stamped_msg(af.pose, pose_hdr, kind=ts))
    result = ConvertResult(
        writer.out,
        len(assoc.frames),
        dict(writer.counts),
        assoc.dropped,
        'groundtruth',
        time.perf_counter() - start,
    )
    logger.debug('wrote %s: %d frames in %.1f s', writer.out, result.frames, result.seconds)
    return result


# --------------------------------------------------------------------------- ROS 1 bag


def _frame_name(name: str) -> str:
    """tf frame names without ROS 1's leading slash."""
    return name.lstrip('/')


class TfTree:
    """Transforms from ``/tf`` and ``/tf_static``, looked up (interpolated) at given stamps.

    Each child frame has one parent (a tf tree). An edge that only ever published one value,
    came from ``/tf_static``, or never changed is constant; others are interpolated (linear
    translation, slerp) and invalid outside the span they were published for.
    """

    def __init__(self) -> None:
        self._edges: dict[str, tuple[str, list[int], list[np.ndarray], bool]] = {}

    def add(
        self, parent: str, child: str, stamp_ns: int, T_parent_child: np.ndarray, static: bool = False
    ) -> None:
        parent, child = _frame_name(parent), _frame_name(child)
        edge = self._edges.setdefault(child, (parent, [], [], static))
        if edge[0] != parent:
            raise ValueError(f'tf frame {child!r} has two parents: {edge[0]!r} and {parent!r}')
        edge[1].append(int(stamp_ns))
        edge[2].append(T_parent_child)

    @property
    def frames(self) -> set[str]:
        return set(self._edges) | {e[0] for e in self._edges.values()}

    def _edge_at(self, child: str, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        _, stamps, poses, static = self._edges[child]
        arr = np.asarray(poses, dtype=np.float64)
        if static or len(arr) == 1 or np.allclose(arr, arr[0], rtol=0.0, atol=1e-12):
            return np.broadcast_to(arr[-1], (len(query_ns), 4, 4)), np.ones(len(query_ns), bool)
        stamps_arr = np.asarray(stamps, dtype=np.int64)
        order = np.argsort(stamps_arr, kind='stable')
        stamps_arr, arr = stamps_arr[order], arr[order]
        keep = np.concatenate(([True], np.diff(stamps_arr) > 0))
        return TumTrajectory(Path('/tf'), stamps_arr[keep], arr[keep]).interpolate(query_ns)

    def lookup(self, target: str, source: str, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T_target_source`` at each stamp, and whether it is known there.

        ``target`` must be an ancestor of ``source`` (e.g. ``world`` -> ... -> camera).
        """
        target, source = _frame_name(target), _frame_name(source)
        query_ns = np.asarray(query_ns, dtype=np.int64)
        T = np.tile(np.eye(4), (len(query_ns), 1, 1))
        valid = np.ones(len(query_ns), bool)
        frame, seen = source, set()
        while frame != target:
            if frame not in self._edges or frame in seen:
                known = ', '.join(sorted(self.frames)) or 'none'
                raise ValueError(f'no /tf chain from {target!r} to {source!r} (frames: {known})')
            seen.add(frame)
            T_edge, ok = self._edge_at(frame, query_ns)
            T = np.einsum('nij,njk->nik', T_edge, T)
            valid &= ok
            frame = self._edges[frame][0]
        T[~valid] = np.nan
        return T, valid


@dataclass
class _Ros1Scan:
    """Everything the first pass over a ROS 1 bag learns (stamps, calibration, poses)."""

    rgb_stamps: list[int] = field(default_factory=list)
    depth_stamps: list[int] = field(default_factory=list)
    calibration: CameraCalibration | None = None
    camera_frame: str | None = None
    pose_stamps: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    tf: TfTree = field(default_factory=TfTree)


def _scan_ros1(reader: AnyReader, src: Path, source: BagTopics) -> _Ros1Scan:
    topics = {c.topic for c in reader.connections}
    if source.rgb not in topics:
        raise ValueError(f'{src}: no colour topic {source.rgb} (it has: {", ".join(sorted(topics))})')
    wanted = {source.rgb, source.depth, source.camera_info, source.pose, *TF_TOPICS}
    scan = _Ros1Scan()
    conns = [c for c in reader.connections if c.topic in wanted]
    for conn, _, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.topic == source.rgb:
            scan.rgb_stamps.append(stamp_to_ns(msg.header.stamp))
            scan.camera_frame = scan.camera_frame or msg.header.frame_id
        elif conn.topic == source.depth:
            scan.depth_stamps.append(stamp_to_ns(msg.header.stamp))
        elif conn.topic == source.camera_info and scan.calibration is None:
            scan.calibration = camera_info_to_calibration(msg)
        elif conn.topic == source.pose:
            scan.pose_stamps.append(stamp_to_ns(msg.header.stamp))
            scan.poses.append(pose_stamped_to_matrix(msg))
        elif conn.topic in TF_TOPICS:
            for tr in msg.transforms:
                scan.tf.add(
                    tr.header.frame_id,
                    tr.child_frame_id,
                    stamp_to_ns(tr.header.stamp),
                    transform_to_matrix(tr.transform),
                    static=conn.topic == '/tf_static',
                )
    return scan


def _ros1_poses(
    scan: _Ros1Scan, query: np.ndarray, groundtruth: Path | None, tf_world: str, tf_camera: str | None
) -> tuple[np.ndarray, np.ndarray, str]:
    """Camera-to-world poses at ``query`` from the best source available, and its name."""
    if groundtruth is not None:
        T, ok = read_groundtruth(groundtruth).interpolate(query)
        return T, ok, f'groundtruth ({groundtruth})'
    if scan.pose_stamps:
        stamps = np.asarray(scan.pose_stamps, dtype=np.int64)
        order = np.argsort(stamps, kind='stable')
        stamps, poses = stamps[order], np.asarray(scan.poses)[order]
        keep = np.concatenate(([True], np.diff(stamps) > 0))
        T, ok = TumTrajectory(Path('pose topic'), stamps[keep], poses[keep]).interpolate(query)
        return T, ok, 'pose topic'
    camera = tf_camera or scan.camera_frame
    if camera and scan.tf.frames:
        T, ok = scan.tf.lookup(tf_world, camera, query)
        return T, ok, f'/tf ({_frame_name(tf_world)} -> {_frame_name(camera)})'
    logger.warning('no ground truth, pose topic or /tf in the bag: writing no poses')
    return np.full((len(query), 4, 4), np.nan), np.zeros(len(query), bool), 'none'


class _OrderedOutput:
    """Buffers serialised messages briefly so they reach the bag in stamp order.

    A depth image is re-stamped with the colour stamp it is associated with, which can be up
    to ``horizon_ns`` earlier or later than the bag position: messages wait in a heap until
    the bag has moved ``horizon_ns`` past them (a handful of frames in memory).
    """

    def __init__(self, writer: AtomicBagWriter, horizon_ns: int) -> None:
        self.writer = writer
        self.horizon_ns = horizon_ns
        self._heap: list[tuple[int, int, str, str, bytes]] = []
        self._seq = 0

    def push(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        data = bytes(self.writer.typestore.serialize_cdr(msg, msgtype))
        heapq.heappush(self._heap, (stamp_ns, self._seq, topic, msgtype, data))
        self._seq += 1

    def advance(self, now_ns: int) -> None:
        while self._heap and self._heap[0][0] < now_ns - self.horizon_ns:
            self._pop()

    def flush(self) -> None:
        while self._heap:
            self._pop()

    def _pop(self) -> None:
        stamp, _, topic, msgtype, data = heapq.heappop(self._heap)
        self.writer.write_raw(topic, msgtype, stamp, data)


def ros1_to_rosbag2(
    src: str | Path,
    out: str | Path,
    *,
    storage: str = 'mcap',
    max_frames: int | None = None,
    topics: BagTopics = BagTopics(),
    source_topics: BagTopics = BagTopics(),
    frame_ids: FrameIds = FrameIds(),
    groundtruth: str | Path | None = None,
    camera_yaml: str | Path | None = None,
    tf_world_frame: str = 'world',
    tf_camera_frame: str | None = None,
    depth_max_gap: float = 0.02,
    include_depth: bool = True,
    overwrite: bool = False,
    show_progress: bool = True,
    colour: ColourFormat = RAW_COLOUR,
) -> ConvertResult:
    """Convert a ROS 1 bag (e.g. a TUM RGB-D ``.bag``) into our rosbag2 layout.

    Colour images (any of rgb8/bgr8/rgba8/bgra8/mono8) become rgb8, depth (32FC1 m or 16UC1 mm)
    becomes 32FC1 metres re-stamped with its nearest colour frame, and one CameraInfo and one
    PoseStamped are written per colour frame. Poses come from, in order of preference: the
    ``groundtruth`` file (TUM format, interpolated at the colour stamps), a PoseStamped topic
    ``source_topics.pose`` in the bag, or the ``/tf`` chain from ``tf_world_frame`` to the
    camera frame (``tf_camera_frame``, default the colour images' frame_id). Intrinsics come
    from ``camera_yaml`` when given (TUM bags carry uncalibrated default intrinsics), else
    from the bag's first CameraInfo.
    """
    start = time.perf_counter()
    src = Path(src)
    if not src.is_file():
        raise FileNotFoundError(f'ROS 1 bag {src} not found')
    if src.suffix != '.bag':
        raise ValueError(f'{src}: a ROS 1 bag must end in .bag')
    if depth_max_gap < 0:
        raise ValueError(f'depth_max_gap must be >= 0, got {depth_max_gap}')
    writer = AtomicBagWriter(out, storage, overwrite)  # fail on an existing output before reading
    with AnyReader([src]) as reader:
        scan = _scan_ros1(reader, src, source_topics)
        calib = read_camera_yaml(camera_yaml) if camera_yaml is not None else scan.calibration
        if calib is None:
            raise ValueError(f'{src}: no CameraInfo on {source_topics.camera_info}; pass --camera-yaml')
        query = np.unique(np.asarray(scan.rgb_stamps, dtype=np.int64))
        gt = Path(groundtruth) if groundtruth is not None else None
        poses, has_pose, pose_source = _ros1_poses(scan, query, gt, tf_world_frame, tf_camera_frame)
        depth_sorted = np.unique(np.asarray(scan.depth_stamps, dtype=np.int64))
        didx, gap = nearest_stamps(depth_sorted, query)
        has_depth = gap <= round(depth_max_gap * NS_PER_SEC)
        if include_depth and not len(depth_sorted):
            raise ValueError(
                f'{src}: no depth images on {source_topics.depth} (pass --no-depth to skip depth)'
            )
        dropped = {'duplicate_stamp': len(scan.rgb_stamps) - len(query), 'outside_poses': 0, 'no_depth': 0}
        selected: dict[int, np.ndarray | None] = {}
        depth_targets: dict[int, list[int]] = {}
        for i, stamp in enumerate(query.tolist()):
            if max_frames is not None and len(selected) >= max_frames:
                break
            if pose_source != 'none' and not has_pose[i]:
                dropped['outside_poses'] += 1
                continue
            if include_depth and not has_depth[i]:
                dropped['no_depth'] += 1
                continue
            selected[stamp] = poses[i] if has_pose[i] else None
            if include_depth:
                depth_targets.setdefault(int(depth_sorted[didx[i]]), []).append(stamp)
        dropped = {k: v for k, v in dropped.items() if v}
        if not selected:
            raise ValueError(f'{src}: no frame to write (poses from {pose_source}; dropped: {dropped})')
        _write_ros1_frames(
            reader,
            writer,
            source_topics,
            topics,
            frame_ids,
            calib,
            selected,
            depth_targets,
            depth_max_gap,
            show_progress,
            colour,
        )
    result = ConvertResult(
        writer.out, len(selected), dict(writer.counts), dropped, pose_source, time.perf_counter() - start
    )
    logger.debug(
        'wrote %s: %d frames (poses: %s) in %.1f s', writer.out, result.frames, pose_source, result.seconds
    )
    return result


def _write_ros1_frames(
    reader: AnyReader,
    writer: AtomicBagWriter,
    source: BagTopics,
    topics: BagTopics,
    frame_ids: FrameIds,
    calib: CameraCalibration,
    selected: dict[int, np.ndarray | None],
    depth_targets: dict[int, list[int]],
    depth_max_gap: float,
    show_progress: bool,
    colour: ColourFormat = RAW_COLOUR,
) -> None:
    """Second pass: convert and write the selected colour frames and their depth."""
    ts = writer.typestore
    cam = calib.camera
    conns = [
        c for c in reader.connections if c.topic == source.rgb or (depth_targets and c.topic == source.depth)
    ]
    total = sum(c.msgcount for c in conns)
    written_rgb: set[int] = set()
    written_depth: set[int] = set()
    with writer:
        out = _OrderedOutput(writer, horizon_ns=round(2 * depth_max_gap * NS_PER_SEC) + NS_PER_SEC // 2)
        messages = progress(
            reader.messages(connections=conns),
            desc='convert',
            unit='msg',
            total=total,
            disable=not show_progress,
        )
        for conn, _, raw in messages:
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = stamp_to_ns(msg.header.stamp)
            if conn.topic == source.rgb and stamp in selected and stamp not in written_rgb:
                rgb = image_to_rgb(msg)
                _check_image_size(rgb, cam, conn.topic, stamp)
                hdr = header_msg(stamp, frame_ids.camera, kind=ts)
                rgb_topic, rgb_type, rgb_msg = colour.message(rgb, hdr, topics.rgb, kind=ts)
                out.push(rgb_topic, rgb_type, stamp, rgb_msg)
                out.push(topics.camera_info, CAMERA_INFO, stamp, camera_info_msg(calib, hdr, kind=ts))
                pose = selected[stamp]
                if pose is not None:
                    pose_hdr = header_msg(stamp, frame_ids.world, kind=ts)
                    out.push(topics.pose, POSE_STAMPED, stamp, pose_stamped_msg(pose, pose_hdr, kind=ts))
                written_rgb.add(stamp)
            elif conn.topic == source.depth and stamp in depth_targets and stamp not in written_depth:
                depth = image_to_depth(msg)
                _check_image_size(depth, cam, conn.topic, stamp)
                for target in depth_targets[stamp]:
                    hdr = header_msg(target, frame_ids.camera, kind=ts)
                    out.push(topics.depth, IMAGE, target, depth_image_msg(depth, hdr, kind=ts))
                written_depth.add(stamp)
            out.advance(stamp)
        out.flush()


def _check_image_size(img: np.ndarray, camera: Any, topic: str, stamp: int) -> None:
    h, w = img.shape[:2]
    if (w, h) != camera.size:
        raise ValueError(
            f'{topic} at {stamp / NS_PER_SEC:.6f}: image is {w}x{h}, '
            f'the calibration is {camera.width}x{camera.height}'
        )


# --------------------------------------------------------------------------- dispatch


def convert(src: str | Path, out: str | Path, **options: Any) -> ConvertResult:
    """Convert a TUM folder or a ROS 1 ``.bag`` into a rosbag2 (options as the two functions).

    Options that only apply to ROS 1 bags (``groundtruth``, ``camera_yaml``,
    ``source_topics``, ``tf_*``) are rejected for a TUM folder rather than silently ignored.
    """
    path = Path(src)
    if path.is_dir():
        if not (path / 'rgb.txt').is_file():
            raise ValueError(f'{path} is neither a TUM folder (no rgb.txt) nor a ROS 1 .bag file')
        ros1_only = ('groundtruth', 'camera_yaml', 'source_topics', 'tf_world_frame', 'tf_camera_frame')
        given = [k for k in ros1_only if options.get(k) is not None]
        if given:
            raise ValueError(f'{", ".join(given)} only apply to a ROS 1 bag source, not to TUM folder {path}')
        return tum_to_rosbag(path, out, **{k: v for k, v in options.items() if k not in ros1_only})
    if path.is_file():
        return ros1_to_rosbag2(path, out, **{k: v for k, v in options.items() if v is not None})
    raise FileNotFoundError(f'source {path} not found')
