"""A converted bag re-recorded as a robot records it: its drivers' topic names, the odometry of
its body instead of the camera pose, and (optionally) depth as a RealSense publishes it (16UC1
millimetres, aligned to the colour camera). What the robot-recording tests of the check
commands and of ``evaluate`` read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from message_kinds import odometry_msg

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.bag_writer import AtomicBagWriter
from depth_fusion_ros.data.rosbag_read import bag_typestore, iter_messages
from depth_fusion_ros.geometry import invert_pose, make_pose, pose_to_tq

#: A camera mounted on a body: 10 cm ahead, 5 cm up, optical axis along the body's x.
T_BODY_CAM = make_pose([0.10, 0.0, 0.05], [-0.5, 0.5, -0.5, 0.5])
#: ``--camera-from-pose-frame`` of that mount.
MOUNT = [str(v) for v in np.concatenate(pose_to_tq(T_BODY_CAM))]
DEPTH_TOPIC = '/cam/aligned_depth_to_color/image_raw'
ROBOT = [
    '--image-topic',
    '/cam/image_raw',
    '--camera-info-topic',
    '/cam/camera_info',
    '--pose-topic',
    '/odom',
]


def robot_bag(bag: Path, out: Path, depth: bool = False, depth_frame: str | None = None) -> Path:
    """``bag`` (the layout ``convert`` writes) as a robot records it: its own topic names, and the
    body's odometry (``T_world_body = T_world_cam @ inv(T_BODY_CAM)``) instead of the camera
    pose; with ``depth``, the depth as 16UC1 mm on :data:`DEPTH_TOPIC` (none otherwise), in the
    colour's frame or in ``depth_frame``."""
    names = {'/camera/rgb/image_color': '/cam/image_raw', '/camera/rgb/camera_info': '/cam/camera_info'}
    T_cam_body = invert_pose(T_BODY_CAM)
    store = bag_typestore()
    with AtomicBagWriter(out) as writer:
        for topic, t_ns, msg in iter_messages(bag):
            if topic == '/camera/pose':
                T_world_body = m.pose_message_to_matrix(msg) @ T_cam_body
                odom = odometry_msg(T_world_body, msg.header, 'base_link', kind=store)
                writer.write('/odom', 'nav_msgs/msg/Odometry', t_ns, odom)
            elif topic in names:
                writer.write(names[topic], msg.__msgtype__, t_ns, msg)
            elif topic == '/camera/depth/image' and depth:
                metres = m.image_to_depth(msg)
                mm = np.where(np.isfinite(metres), np.round(metres * 1000.0), 0).astype(np.uint16)
                header = msg.header
                if depth_frame is not None:
                    header = m.header_msg(m.stamp_to_ns(msg.header.stamp), depth_frame, kind=store)
                writer.write(DEPTH_TOPIC, msg.__msgtype__, t_ns, m.image_msg(mm, '16UC1', header, kind=store))
    return out
