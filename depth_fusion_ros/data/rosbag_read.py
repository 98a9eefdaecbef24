"""Read rosbag2 recordings (mcap or sqlite3) back: decoded messages, depth images, a Sequence.

No rclpy needed: messages are decoded with rosbags' ROS 2 Jazzy typestore, and converted with
``data.messages`` (which reads rosbags objects exactly like rclpy ones).

* ``iter_messages(bag, topics)`` yields ``(topic, log_time_ns, message)``;
* ``read_depth_images(bag, topic)`` collects recorded depth (e.g. the fused output) keyed by
  header stamp in nanoseconds;
* ``load_bag_sequence(bag, ...)`` rebuilds an evaluation ``Sequence`` from the colour,
  camera-info, pose and ground-truth depth topics that ``depth-fusion convert`` writes (colour
  raw, or CompressedImage on ``<rgb topic>/compressed`` when the raw topic is absent),
  undistorting with the CameraInfo's D exactly like ``load_tum_sequence`` does.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from collections.abc import Sequence as Seq
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from .bag_recovery import open_rosbag2, readable_rosbag2
from .compressed import any_image_to_rgb, colour_topic_in
from .messages import (
    camera_info_to_calibration,
    image_to_depth,
    pose_message_to_matrix,
    stamp_to_ns,
)
from .sequence import Frame, Sequence
from .tum import TumTrajectory, nearest_stamps
from .undistort import CameraCalibration, Undistorter

logger = logging.getLogger(__name__)

#: Default topics, as written by ``depth-fusion convert`` (docs/ARCHITECTURE.md).
RGB_TOPIC = '/camera/rgb/image_color'
CAMERA_INFO_TOPIC = '/camera/rgb/camera_info'
DEPTH_TOPIC = '/camera/depth/image'
POSE_TOPIC = '/camera/pose'

NS_PER_SEC = 1_000_000_000
_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def bag_typestore() -> Any:
    """The typestore used to decode and encode bags (ROS 2 Jazzy)."""
    return _TYPESTORE


def _check_bag(bag: str | Path) -> Path:
    path = Path(bag)
    if not path.exists():
        raise FileNotFoundError(f'bag {path} not found')
    if not readable_rosbag2(path):
        raise ValueError(
            f'{path} is not a rosbag2 folder (no metadata.yaml); ROS 1 bags: run depth-fusion convert'
        )
    return path


def bag_topics(bag: str | Path) -> dict[str, tuple[str, int]]:
    """``{topic: (msgtype, message count)}`` of a rosbag2."""
    with closing(open_rosbag2(_check_bag(bag))) as reader:
        return {name: (info.msgtype, info.msgcount) for name, info in reader.topics.items()}


def iter_messages(bag: str | Path, topics: Seq[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """Decoded messages ``(topic, log_time_ns, msg)`` of ``topics`` (all when ``None``).

    A requested topic that is not in the bag raises ``ValueError`` listing the topics it has.
    """
    path = _check_bag(bag)
    with closing(open_rosbag2(path)) as reader:
        if topics is not None:
            missing = sorted(set(topics) - set(reader.topics))
            if missing:
                raise ValueError(
                    f'{path}: no topic {", ".join(missing)} (it has: {", ".join(sorted(reader.topics))})'
                )
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        for conn, timestamp, raw in reader.messages(connections=conns):
            yield conn.topic, timestamp, _TYPESTORE.deserialize_cdr(raw, conn.msgtype)


def read_depth_images(bag: str | Path, topic: str) -> dict[int, np.ndarray]:
    """Depth images (float32 metres, NaN = none) of ``topic`` keyed by header stamp (ns)."""
    return {stamp_to_ns(msg.header.stamp): image_to_depth(msg) for _, _, msg in iter_messages(bag, [topic])}


def read_poses(bag: str | Path, topic: str = POSE_TOPIC) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps_ns (N,) int64, T_wc (N, 4, 4))`` of a pose topic (PoseStamped,
    PoseWithCovarianceStamped, Odometry or TransformStamped: ``pose_message_to_matrix``),
    sorted by stamp."""
    stamps, poses = [], []
    for _, _, msg in iter_messages(bag, [topic]):
        stamps.append(stamp_to_ns(msg.header.stamp))
        poses.append(pose_message_to_matrix(msg))
    samples = TumTrajectory.from_samples(topic, stamps, poses)
    return samples.stamps_ns, samples.poses


def _scan(
    path: Path, rgb_topic: str, info_topic: str | None, pose_topic: str, depth_topic: str | None
) -> tuple[list[int], list[int], CameraCalibration | None, np.ndarray, np.ndarray]:
    """First pass: header stamps of colour and depth, the first CameraInfo, all poses."""
    rgb_stamps: list[int] = []
    depth_stamps: list[int] = []
    calib: CameraCalibration | None = None
    pose_stamps, poses = [], []
    frames: dict[str, str] = {}  # the first frame_id of the colour and of the depth
    topics = [t for t in (rgb_topic, info_topic, pose_topic, depth_topic) if t]
    for topic, _, msg in iter_messages(path, topics):
        if topic in (rgb_topic, depth_topic):
            frames.setdefault(topic, msg.header.frame_id)
        if topic == rgb_topic:
            rgb_stamps.append(stamp_to_ns(msg.header.stamp))
        elif topic == depth_topic:
            depth_stamps.append(stamp_to_ns(msg.header.stamp))
        elif topic == info_topic and calib is None:
            calib = camera_info_to_calibration(msg)
        elif topic == pose_topic:
            pose_stamps.append(stamp_to_ns(msg.header.stamp))
            poses.append(pose_message_to_matrix(msg))
    _warn_unregistered(path, frames.get(rgb_topic, ''), depth_topic, frames.get(depth_topic, ''))
    samples = TumTrajectory.from_samples(pose_topic, pose_stamps, poses)
    return rgb_stamps, depth_stamps, calib, samples.stamps_ns, samples.poses


def _warn_unregistered(path: Path, colour_frame: str, depth_topic: str | None, depth_frame: str) -> None:
    """Say when the depth is in another optical frame than the colour: the scores and every
    depth check read it as registered to the colour camera (a RealSense's
    ``aligned_depth_to_color``, not its ``depth/image_rect_raw``). A warning, not an error: a
    registered depth may keep its sensor's frame_id (TUM's ``openni_depth_optical_frame``)."""
    if depth_topic and colour_frame and depth_frame and colour_frame != depth_frame:
        logger.warning(
            '%s: the depth on %s is in frame %r, the colour in %r: it is read as registered to the '
            'colour camera (same pixels); if it is not, the scores against it are wrong',
            path.name,
            depth_topic,
            depth_frame,
            colour_frame,
        )


def load_bag_sequence(
    bag: str | Path,
    width: int = 320,
    height: int = 240,
    max_frames: int | None = None,
    rgb_topic: str = RGB_TOPIC,
    camera_info_topic: str | None = CAMERA_INFO_TOPIC,
    pose_topic: str = POSE_TOPIC,
    depth_topic: str | None = DEPTH_TOPIC,
    require_depth: bool = True,
    depth_max_gap: float = 0.02,
    calibration: CameraCalibration | None = None,
    undistort: bool = True,
) -> Sequence:
    """A ``Sequence`` from a rosbag2 (the layout ``depth-fusion convert`` writes).

    Colour frames get the pose interpolated at their stamp (dropped: ``no_pose``) and the
    nearest depth image within ``depth_max_gap`` s (dropped: ``no_depth`` when
    ``require_depth``). Intrinsics and distortion come from the first CameraInfo unless
    ``calibration`` is given. Frames are returned like ``load_tum_sequence``'s: RGB
    undistorted at ``width x height``, depth undistorted at the CameraInfo resolution.
    """
    path = _check_bag(bag)
    if depth_topic is None:
        require_depth = False
    rgb_topic = colour_topic_in(bag_topics(path), rgb_topic)  # raw, else <rgb>/compressed
    rgb_stamps, depth_stamps, calib, pose_stamps, poses = _scan(
        path, rgb_topic, camera_info_topic if calibration is None else None, pose_topic, depth_topic
    )
    if calibration is not None and any(calibration.centre_in_depth_camera):
        raise ValueError(
            f"{path}: the colour calibration gives centre_in_depth_camera, but a bag's depth is read as "
            "registered to the colour camera already (the centre registers a TUM folder's depth camera)"
        )
    calib = calibration or calib
    if calib is None:
        raise ValueError(f'{path}: no CameraInfo on {camera_info_topic}; pass a calibration')
    query = np.unique(np.asarray(rgb_stamps, dtype=np.int64))
    dropped = {'duplicate_stamp': len(rgb_stamps) - len(query), 'no_pose': 0, 'no_depth': 0}
    T, has_pose = TumTrajectory(path, pose_stamps, poses).interpolate(query)
    depth_sorted = np.unique(np.asarray(depth_stamps, dtype=np.int64))
    didx, gap = nearest_stamps(depth_sorted, query)
    has_depth = gap <= round(depth_max_gap * NS_PER_SEC)
    selected: list[tuple[int, np.ndarray, int | None]] = []
    for i, stamp in enumerate(query.tolist()):
        if max_frames is not None and len(selected) >= max_frames:
            break
        if not has_pose[i]:
            dropped['no_pose'] += 1
        elif require_depth and not has_depth[i]:
            dropped['no_depth'] += 1
        else:
            selected.append((stamp, T[i], int(depth_sorted[didx[i]]) if has_depth[i] else None))
    model_D = calib.D if undistort else ()
    und = Undistorter.for_calibration(
        CameraCalibration(calib.camera, calib.distortion_model, model_D), width, height
    )
    want_rgb = {s for s, _, _ in selected}
    want_depth = {d for _, _, d in selected if d is not None}
    rgb: dict[int, np.ndarray] = {}
    depth: dict[int, np.ndarray] = {}
    topics = [rgb_topic] + ([depth_topic] if want_depth else [])
    for topic, _, msg in iter_messages(path, topics):
        stamp = stamp_to_ns(msg.header.stamp)
        if topic == rgb_topic and stamp in want_rgb and stamp not in rgb:
            rgb[stamp] = und.rgb(any_image_to_rgb(msg))
        elif topic == depth_topic and stamp in want_depth and stamp not in depth:
            depth[stamp] = und.depth(image_to_depth(msg))
    frames = [
        Frame(
            index=i,
            stamp=s / NS_PER_SEC,
            rgb=rgb[s],
            pose=pose,
            depth=depth.get(d) if d is not None else None,
        )
        for i, (s, pose, d) in enumerate(selected)
    ]
    dropped = {k: v for k, v in dropped.items() if v}
    if dropped:
        logger.info('%s: dropped frames %s', path.name, dropped)
    stream = (pose_stamps / 1e9, poses) if len(pose_stamps) else None
    return Sequence(
        name=path.name,
        camera=und.camera,
        frames=frames,
        gt_camera=und.native_camera,
        dropped=dropped,
        pose_stream=stream,
    )
