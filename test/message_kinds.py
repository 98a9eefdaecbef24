"""The message kinds the conversion tests run on: rosbags dataclasses, and rclpy classes where
rclpy is installed (a rosbags-only install has none)."""

from __future__ import annotations

from rosbags.typesys import Stores, get_typestore

from depth_fusion_ros.data import messages as m

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def _kinds() -> list:
    kinds = [TYPESTORE]
    try:
        import rclpy  # noqa: F401

        kinds.append(m.RCLPY)
    except ImportError:  # pragma: no cover - the venv has rclpy; rosbags-only installs do not
        pass
    return kinds


KINDS = _kinds()
KIND_IDS = ['rosbags' if k is TYPESTORE else 'rclpy' for k in KINDS]


def odometry_msg(T, header, child_frame_id: str, *, kind) -> object:
    """A nav_msgs/Odometry of pose ``T`` (zero covariances and twist) in any message kind: what
    the pose-type tests feed a node, a converter or a recording."""
    import numpy as np

    k = m.as_kind(kind)
    zero = k.new('geometry_msgs/msg/Vector3', x=0.0, y=0.0, z=0.0)
    twist = k.new(
        'geometry_msgs/msg/TwistWithCovariance',
        twist=k.new('geometry_msgs/msg/Twist', linear=zero, angular=zero),
        covariance=np.zeros(36),
    )
    pose = k.new('geometry_msgs/msg/PoseWithCovariance', pose=m.pose_msg(T, kind=k), covariance=np.zeros(36))
    odometry = 'nav_msgs/msg/Odometry'
    return k.new(odometry, header=header, child_frame_id=child_frame_id, pose=pose, twist=twist)
