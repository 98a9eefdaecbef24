"""One recording read as a ``Sequence``: a TUM folder or a robot's rosbag2, with its own topics.

Why one loader: ``evaluate``, ``adapt`` and the calibration checks (``check-focal``,
``check-sync``, ``check-mount``) all take "a recording", and a robot's ``ros2 bag record``
names its topics after its drivers (``/camera/color/image_raw``,
``/camera/aligned_depth_to_color/image_raw``, ``/odom``), not after the layout
``depth-fusion convert`` writes. So the topics are options, the poses may be a body's
(``camera_from_pose_frame``, as multi_view_node's parameter), and every command reads a
recording the same way.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..geometry import transform_from_parameter
from .bag_recovery import readable_rosbag2
from .sequence import Sequence
from .undistort import CameraCalibration

#: The topic options of a recording and the ``load_bag_sequence`` keywords they set.
TOPIC_KEYWORDS = {
    'image_topic': 'rgb_topic',
    'camera_info_topic': 'camera_info_topic',
    'pose_topic': 'pose_topic',
    'depth_topic': 'depth_topic',
}


def load_recording(
    source: str | Path,
    width: int,
    height: int,
    max_frames: int | None,
    *,
    calibration: CameraCalibration | None = None,
    topics: Mapping[str, str] | None = None,
    camera_from_pose_frame: list[float] | None = None,
    with_depth: bool = True,
) -> Sequence:
    """``source`` (TUM folder or rosbag2) at ``width x height``, its poses the camera's.

    ``topics``: :data:`TOPIC_KEYWORDS` names to topics, for a rosbag2 only (given for a TUM
    folder: ``ValueError`` naming them); those not given are ``depth-fusion convert``'s.
    ``with_depth``: ground-truth depth is read and a frame without it dropped (``evaluate``);
    without, no depth is read (the checks).
    """
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f'{source} does not exist')
    given = {name: topic for name, topic in (topics or {}).items() if topic}
    unknown = sorted(set(given) - set(TOPIC_KEYWORDS))
    if unknown:
        raise ValueError(f'unknown topic option(s) {unknown}; known: {sorted(TOPIC_KEYWORDS)}')
    if readable_rosbag2(source):
        from .rosbag_read import load_bag_sequence

        keywords = {TOPIC_KEYWORDS[name]: topic for name, topic in given.items()}
        if not with_depth:
            keywords['depth_topic'] = None
        sequence = load_bag_sequence(
            source, width, height, max_frames, calibration=calibration, require_depth=with_depth, **keywords
        )
    else:
        if given:
            named = ', '.join('--' + name.replace('_', '-') for name in given)
            raise ValueError(f'{named}: topics are for a rosbag2, and {source} is a TUM folder')
        from .tum import load_tum_sequence

        sequence = load_tum_sequence(
            source, width, height, max_frames, require_depth=with_depth, rgb_calibration=calibration
        )
    return camera_poses(sequence, camera_from_pose_frame)


def camera_poses(sequence: Sequence, camera_from_pose_frame: list[float] | None) -> Sequence:
    """``sequence`` with its poses (and its pose record) taken from the poses' frame to the camera
    optical frame, ``T_world_cam = T_world_pose @ T_pose_cam``, as multi_view_node does; as it
    is without one."""
    if camera_from_pose_frame is None:
        return sequence
    T_pose_cam = transform_from_parameter(list(camera_from_pose_frame), '--camera-from-pose-frame')
    stream = sequence.pose_stream
    moved = None if stream is None else (stream[0], np.asarray(stream[1]) @ T_pose_cam)
    return sequence.with_poses(sequence.poses @ T_pose_cam, pose_stream=moved)
