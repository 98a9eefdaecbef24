"""The layout a converted bag has: its topic names, frame ids, message types and what was written.

Kept apart from the converters so the TUM and ROS 1 converters and the ``rosbag_convert``
front door share one definition without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

NS_PER_SEC = 1_000_000_000
IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'


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
    """What a conversion wrote (``pose_source`` also says whether the poses are the source's
    own samples or interpolated at the colour stamps)."""

    path: Path
    frames: int
    messages: dict[str, int]
    dropped: dict[str, int] = field(default_factory=dict)
    pose_source: str = 'groundtruth'
    seconds: float = 0.0


#: The defaults, shared by the converters' signatures (one immutable instance each).
DEFAULT_TOPICS = BagTopics()
DEFAULT_FRAME_IDS = FrameIds()
