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
