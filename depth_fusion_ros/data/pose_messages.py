"""``geometry_msgs`` poses and transforms <-> 4x4 matrices (PoseStamped, Odometry, TransformStamped ...).

Readers validate (``geometry.PoseError``) rather than renormalise: a broken pose source must be
noticed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..geometry import PoseError, pose_to_tq, quat_to_matrix, validate_pose
from .message_kinds import as_kind
from .message_stamps import _header_for


def _quat_xyzw(q: Any) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=np.float64)


def _rigid_to_matrix(translation: Any, rotation: Any, what: str) -> np.ndarray:
    t = np.array([translation.x, translation.y, translation.z], dtype=np.float64)
    if not np.all(np.isfinite(t)):
        raise PoseError(f'{what} has non-finite values: {t.tolist()}')
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(_quat_xyzw(rotation), normalise=False)
    T[:3, 3] = t
    return T


def pose_to_matrix(pose: Any) -> np.ndarray:
    """4x4 transform of a ``geometry_msgs/Pose``.

    Raises ``geometry.PoseError`` for NaN/Inf values or a quaternion that is not unit length
    (a broken pose source must be noticed, not silently renormalised).
    """
    return _rigid_to_matrix(pose.position, pose.orientation, 'pose position')


def transform_to_matrix(transform: Any) -> np.ndarray:
    """4x4 transform of a ``geometry_msgs/Transform`` (as in ``/tf``); same checks as poses."""
    return _rigid_to_matrix(transform.translation, transform.rotation, 'transform translation')


def pose_stamped_to_matrix(msg: Any) -> np.ndarray:
    """4x4 camera-to-world ``T_wc`` of a ``geometry_msgs/PoseStamped``."""
    return pose_to_matrix(msg.pose)


def pose_message_to_matrix(msg: Any) -> np.ndarray:
    """4x4 pose of a PoseStamped, PoseWithCovarianceStamped, nav_msgs/Odometry or TransformStamped.

    The second and third nest the ``Pose`` one level deeper (``msg.pose.pose``); the covariance
    and Odometry's twist are not used. A TransformStamped (a motion-capture bridge's body, a
    ``/tf`` entry on a topic of its own) holds a ``Transform`` instead. The pose is that of the
    message's frame (``child_frame_id`` for Odometry and TransformStamped) in ``header.frame_id``.
    """
    if hasattr(msg, 'transform'):
        return transform_to_matrix(msg.transform)
    pose = msg.pose
    return pose_to_matrix(pose.pose if hasattr(pose, 'pose') else pose)


def pose_msg(T: np.ndarray, *, kind: Any) -> Any:
    """A ``geometry_msgs/Pose`` of a 4x4 rigid transform (validated)."""
    k = as_kind(kind)
    t, q = pose_to_tq(validate_pose(T))
    position = k.new('geometry_msgs/msg/Point', x=float(t[0]), y=float(t[1]), z=float(t[2]))
    orientation = k.new(
        'geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
    )
    return k.new('geometry_msgs/msg/Pose', position=position, orientation=orientation)


def pose_stamped_msg(T_wc: np.ndarray, header: Any, *, kind: Any) -> Any:
    """A ``geometry_msgs/PoseStamped`` of a camera-to-world pose (frame = ``header.frame_id``)."""
    k = as_kind(kind)
    return k.new('geometry_msgs/msg/PoseStamped', header=_header_for(header, k), pose=pose_msg(T_wc, kind=k))
