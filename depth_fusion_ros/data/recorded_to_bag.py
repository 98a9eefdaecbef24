"""A recorded bag -> a rosbag2 in our layout: a ROS 1 ``.bag`` (e.g. a TUM RGB-D sequence as
downloaded) or a robot's own rosbag2 (``ros2 bag record``).

Why both in one place: rosbags' ``AnyReader`` reads either, and both hold what a robot
records: its drivers' topic names, colour raw or as ``<topic>/compressed``, depth in 16UC1
mm, and poses on a topic of their own or only as a ``/tf`` chain (which the nodes cannot
subscribe to: ``tf2_msgs`` is not on pip). The output is the layout ``run``, ``evaluate`` and
the nodes read.

Two passes over the source: the first learns the stamps, the calibration and the poses
(``_scan_recording``) and decides which colour frames to write; the second converts those frames
and their depth, interleaved with the pose source's own samples (``recorded_poses``) in stamp
order through ``OrderedOutput``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader

from ..progress import progress
from .bag_layout import (
    CAMERA_INFO,
    DEFAULT_FRAME_IDS,
    DEFAULT_TOPICS,
    IMAGE,
    NS_PER_SEC,
    POSE_STAMPED,
    BagTopics,
    ConvertResult,
    FrameIds,
)
from .bag_recovery import storage_file
from .bag_writer import AtomicBagWriter, OrderedOutput
from .compressed import RAW_COLOUR, ColourFormat, any_image_to_rgb, colour_topic_in
from .messages import (
    camera_info_msg,
    camera_info_to_calibration,
    depth_image_msg,
    header_msg,
    image_to_depth,
    pose_message_to_matrix,
    pose_stamped_msg,
    stamp_to_ns,
    transform_to_matrix,
)
from .pose_samples import SampleFeed, samples_spanning
from .recorded_poses import PoseSource, recorded_pose_source
from .rosbag_read import bag_typestore
from .tf_tree import TfTree
from .tum import TumTrajectory, nearest_stamps, read_camera_yaml
from .undistort import CameraCalibration

logger = logging.getLogger(__name__)

TF_TOPICS = ('/tf', '/tf_static')


@dataclass
class _RecordingScan:
    """Everything the first pass over a recorded bag learns (stamps, calibration, poses)."""

    rgb_stamps: list[int] = field(default_factory=list)
    depth_stamps: list[int] = field(default_factory=list)
    calibration: CameraCalibration | None = None
    camera_frame: str | None = None
    pose_stamps: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    tf: TfTree = field(default_factory=TfTree)


def colour_source(reader: AnyReader, src: Path, source: BagTopics) -> BagTopics:
    """``source`` with its colour topic as recorded: raw, else ``<topic>/compressed`` (what
    image_transport records); a ``ValueError`` listing the bag's topics when it has neither."""
    topics = {c.topic for c in reader.connections}
    rgb = colour_topic_in(topics, source.rgb)
    if rgb not in topics:
        raise ValueError(f'{src}: no colour topic {source.rgb} (it has: {", ".join(sorted(topics))})')
    return dataclasses.replace(source, rgb=rgb)


def _scan_recording(reader: AnyReader, src: Path, source: BagTopics) -> _RecordingScan:
    wanted = {source.rgb, source.depth, source.camera_info, source.pose, *TF_TOPICS}
    scan = _RecordingScan()
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
            scan.poses.append(pose_message_to_matrix(msg))
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


@dataclass
class _Plan:
    """What the second pass writes: the colour frames (each with the pose to write alongside,
    ``None`` when the source's own ``samples`` are written instead or there is no pose), the
    depth images to re-stamp with their colour frames, and what was dropped."""

    frames: dict[int, np.ndarray | None] = field(default_factory=dict)
    depth_targets: dict[int, list[int]] = field(default_factory=dict)
    samples: TumTrajectory | None = None
    dropped: dict[str, int] = field(default_factory=dict)


def _plan(
    scan: _RecordingScan,
    query: np.ndarray,
    poses: PoseSource,
    depth_max_gap: float,
    include_depth: bool,
    max_frames: int | None,
) -> _Plan:
    """Choose the colour frames (pose and depth found, in order, at most ``max_frames``)."""
    depth_sorted = np.unique(np.asarray(scan.depth_stamps, dtype=np.int64))
    didx, gap = nearest_stamps(depth_sorted, query)
    has_depth = gap <= round(depth_max_gap * NS_PER_SEC)
    dropped = {'duplicate_stamp': len(scan.rgb_stamps) - len(query), 'outside_poses': 0, 'no_depth': 0}
    plan = _Plan()
    for i, stamp in enumerate(query.tolist()):
        if max_frames is not None and len(plan.frames) >= max_frames:
            break
        if poses.found and not poses.valid[i]:
            dropped['outside_poses'] += 1
            continue
        if include_depth and not has_depth[i]:
            dropped['no_depth'] += 1
            continue
        with_frame = poses.samples is None and poses.valid[i]
        plan.frames[stamp] = poses.at_frames[i] if with_frame else None
        if include_depth:
            plan.depth_targets.setdefault(int(depth_sorted[didx[i]]), []).append(stamp)
    plan.dropped = {k: v for k, v in dropped.items() if v}
    if plan.frames and poses.samples is not None:
        plan.samples = samples_spanning(poses.samples, min(plan.frames), max(plan.frames))
    return plan


def recorded_to_rosbag2(
    src: str | Path,
    out: str | Path,
    *,
    storage: str = 'mcap',
    max_frames: int | None = None,
    topics: BagTopics = DEFAULT_TOPICS,
    source_topics: BagTopics = DEFAULT_TOPICS,
    frame_ids: FrameIds = DEFAULT_FRAME_IDS,
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
    """Convert a recorded bag, a ROS 1 ``.bag`` (e.g. a TUM RGB-D sequence) or a rosbag2 folder
    (a robot's ``ros2 bag record``), into our rosbag2 layout.

    Colour images (any encoding of ``messages.COLOUR_ENCODINGS``, or a CompressedImage on
    ``<rgb topic>/compressed`` when the raw topic is absent) become rgb8, depth (32FC1 m or
    16UC1 mm) becomes 32FC1 metres re-stamped with its nearest colour frame, and one CameraInfo is
    written per colour frame. Poses come from, in order of preference: the ``groundtruth``
    file (TUM format), a pose topic ``source_topics.pose`` in the bag (PoseStamped,
    PoseWithCovarianceStamped, Odometry or TransformStamped), or the ``/tf``
    chain from ``tf_world_frame`` to the camera frame (``tf_camera_frame``, default the colour
    images' frame_id). The first two write their own samples spanning the frames, at their own
    stamps; the ``/tf`` chain writes one pose per colour frame, interpolated at its stamp.
    Intrinsics come from ``camera_yaml`` when given (TUM bags carry uncalibrated default
    intrinsics), else from the bag's first CameraInfo.
    """
    start = time.perf_counter()
    src = Path(src)
    _check_recorded(src)
    if depth_max_gap < 0:
        raise ValueError(f'depth_max_gap must be >= 0, got {depth_max_gap}')
    writer = AtomicBagWriter(out, storage, overwrite)  # fail on an existing output before reading
    with AnyReader([src], default_typestore=bag_typestore()) as reader:
        source_topics = colour_source(reader, src, source_topics)
        scan = _scan_recording(reader, src, source_topics)
        calib = read_camera_yaml(camera_yaml) if camera_yaml is not None else scan.calibration
        if calib is None:
            raise ValueError(f'{src}: no CameraInfo on {source_topics.camera_info}; pass --camera-yaml')
        query = np.unique(np.asarray(scan.rgb_stamps, dtype=np.int64))
        poses = recorded_pose_source(
            query,
            groundtruth=Path(groundtruth) if groundtruth is not None else None,
            pose_stamps=scan.pose_stamps,
            poses=scan.poses,
            tf=scan.tf,
            tf_world=tf_world_frame,
            tf_camera=tf_camera_frame or scan.camera_frame,
        )
        if include_depth and not scan.depth_stamps:
            raise ValueError(
                f'{src}: no depth images on {source_topics.depth} (pass --no-depth to skip depth)'
            )
        plan = _plan(scan, query, poses, depth_max_gap, include_depth, max_frames)
        if not plan.frames:
            raise ValueError(f'{src}: no frame to write (poses from {poses.name}; dropped: {plan.dropped})')
        _write_frames(
            reader,
            writer,
            source_topics,
            topics,
            frame_ids,
            calib,
            plan,
            depth_max_gap,
            show_progress,
            colour,
        )
    result = ConvertResult(
        writer.out,
        len(plan.frames),
        dict(writer.counts),
        plan.dropped,
        poses.name,
        time.perf_counter() - start,
    )
    logger.debug(
        'wrote %s: %d frames (poses: %s) in %.1f s', writer.out, result.frames, poses.name, result.seconds
    )
    return result


def _write_frames(
    reader: AnyReader,
    writer: AtomicBagWriter,
    source: BagTopics,
    topics: BagTopics,
    frame_ids: FrameIds,
    calib: CameraCalibration,
    plan: _Plan,
    depth_max_gap: float,
    show_progress: bool,
    colour: ColourFormat = RAW_COLOUR,
) -> None:
    """Second pass: convert and write the planned colour frames, their depth and the poses."""
    ts = writer.typestore
    cam = calib.camera
    selected, depth_targets = plan.frames, plan.depth_targets
    conns = [
        c for c in reader.connections if c.topic == source.rgb or (depth_targets and c.topic == source.depth)
    ]
    total = sum(c.msgcount for c in conns)
    written_rgb: set[int] = set()
    written_depth: set[int] = set()
    with writer:
        out = OrderedOutput(writer, horizon_ns=round(2 * depth_max_gap * NS_PER_SEC) + NS_PER_SEC // 2)
        samples = SampleFeed(plan.samples, topics, frame_ids, ts) if plan.samples is not None else None
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
            if samples is not None:
                for pose in samples.until(stamp):
                    out.push(*pose)
            if conn.topic == source.rgb and stamp in selected and stamp not in written_rgb:
                rgb = any_image_to_rgb(msg)
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
        if samples is not None:
            for pose in samples.until():
                out.push(*pose)
        out.flush()


def _check_recorded(src: Path) -> None:
    """A ROS 1 ``.bag`` file or a rosbag2 folder, or the error that says which it is not."""
    if not src.exists():
        raise FileNotFoundError(f'recorded bag {src} not found')
    if src.is_file():
        if src.suffix != '.bag':
            raise ValueError(f'{src}: a ROS 1 bag must end in .bag (a rosbag2 is its folder)')
        return
    if not (src / 'metadata.yaml').is_file():
        hint = ' (a recording cut short: depth-fusion convert --repair it first)' if storage_file(src) else ''
        raise ValueError(f'{src}: a folder without metadata.yaml is not a rosbag2{hint}')


def _check_image_size(img: np.ndarray, camera: Any, topic: str, stamp: int) -> None:
    h, w = img.shape[:2]
    if (w, h) != camera.size:
        raise ValueError(
            f'{topic} at {stamp / NS_PER_SEC:.6f}: image is {w}x{h}, '
            f'the calibration is {camera.width}x{camera.height}'
        )
