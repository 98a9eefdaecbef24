"""numpy <-> ROS messages, for rclpy message classes *and* rosbags message objects.

The nodes publish rclpy messages; the bag converter and reader work with rosbags
dataclasses (no rclpy needed). Both have the same field names but are built differently
(rosbags dataclasses need every field and hold ``uint8[]`` as numpy arrays; rclpy messages
default every field and hold ``uint8[]`` as ``array.array``). A *message kind* hides that:

    from depth_fusion_ros.data import messages as m
    hdr = m.header_msg(stamp_ns, 'camera_rgb_optical_frame', kind=m.RCLPY)
    msg = m.image_msg(rgb, 'rgb8', hdr, kind=m.RCLPY)                # rclpy
    msg = m.image_msg(rgb, 'rgb8', hdr, kind=typestore)               # rosbags (any Typestore)
    rgb = m.image_to_rgb(msg)                                         # works on both

Readers (``image_to_numpy``, ``camera_info_to_calibration``, ``pose_stamped_to_matrix`` ...)
only read attributes, so they accept either kind, and ROS 1 messages decoded by rosbags too
(``CameraInfo.K``/``D`` upper case). rclpy is imported lazily, on first use of ``RCLPY``.

Stamps: a ``builtin_interfaces/Time`` is converted to *integer nanoseconds* exactly
(``stamp_to_ns``); float seconds are for the core, and ``sec_to_ns`` / ``ns_to_sec``
round-trip a float stamp such as TUM's ``1305031102.175304`` without drift.

This module is the single import surface; the code lives in one file per idea:
``message_kinds`` (rclpy / rosbags kinds), ``message_stamps`` (stamps and headers),
``image_messages``, ``camera_info_messages``, ``pose_messages`` and ``cloud_messages``.
"""

from __future__ import annotations

from .camera_info_messages import (
    camera_info_msg,
    camera_info_to_calibration,
    camera_info_window,
)
from .cloud_messages import POINTFIELD_FLOAT32, pack_rgb, pointcloud2_msg, pointcloud2_to_numpy
from .image_messages import (
    COLOUR_ENCODINGS,
    ENCODINGS,
    PLANAR_YUV,
    depth_image_msg,
    image_msg,
    image_to_depth,
    image_to_numpy,
    image_to_rgb,
    rgb_image_msg,
)
from .message_kinds import RCLPY, MessageKind, RclpyKind, TypestoreKind, as_kind
from .message_stamps import (
    NS_PER_SEC,
    header_msg,
    ns_to_sec,
    sec_to_ns,
    stamp_to_ns,
    stamp_to_sec,
    time_msg,
)
from .pose_messages import (
    pose_message_to_matrix,
    pose_msg,
    pose_stamped_msg,
    pose_stamped_to_matrix,
    pose_to_matrix,
    transform_to_matrix,
)

__all__ = [
    'COLOUR_ENCODINGS',
    'ENCODINGS',
    'NS_PER_SEC',
    'PLANAR_YUV',
    'POINTFIELD_FLOAT32',
    'RCLPY',
    'MessageKind',
    'RclpyKind',
    'TypestoreKind',
    'as_kind',
    'camera_info_msg',
    'camera_info_to_calibration',
    'camera_info_window',
    'depth_image_msg',
    'header_msg',
    'image_msg',
    'image_to_depth',
    'image_to_numpy',
    'image_to_rgb',
    'ns_to_sec',
    'pack_rgb',
    'pointcloud2_msg',
    'pointcloud2_to_numpy',
    'pose_message_to_matrix',
    'pose_msg',
    'pose_stamped_msg',
    'pose_stamped_to_matrix',
    'pose_to_matrix',
    'rgb_image_msg',
    'sec_to_ns',
    'stamp_to_ns',
    'stamp_to_sec',
    'time_msg',
    'transform_to_matrix',
]
