"""The corrected-trajectory input (a SLAM's loop closure), shared by ``multi_view_node`` and
``map_node``: its topic, its parameters (one spelling and one range, each node saying what a
correction makes it do) and the parsing of a ``nav_msgs/Path`` into stamps and poses."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..data import messages
from ..pose_corrections import CorrectionLimits
from . import robot_inputs
from .image_input import InputError, pose_from_message
from .params import ParamSpec

#: ``nav_msgs/Path``: one PoseStamped per pose, at the pose source's own stamps, in the world
#: frame of the poses (remap it to the SLAM's topic).
TOPIC_CORRECTED_PATH = 'camera/corrected_path'


def correction_parameters(consequence: str) -> tuple[ParamSpec, ...]:
    """``correction_min_translation``, ``correction_min_rotation_deg`` and ``correction_max_gap``;
    a correction at least that large has ``consequence`` (said in the description)."""
    return (
        ParamSpec(
            'correction_min_translation',
            CorrectionLimits.min_m,
            f'a corrected trajectory on {TOPIC_CORRECTED_PATH} that moves a pose by at least this (m) '
            f'{consequence} ...',
            0.0,
        ),
        ParamSpec(
            'correction_min_rotation_deg',
            CorrectionLimits.min_deg,
            '... or by at least this (degrees)',
            0.0,
            180.0,
        ),
        ParamSpec(
            'correction_max_gap',
            CorrectionLimits.max_gap,
            'longest gap (s) between two of our poses that a pose of the corrected trajectory is compared '
            'across',
            0.0,
        ),
    )


def _robot_input_parameter(name: str, here: str) -> ParamSpec:
    """``name`` as ``multi_view_node`` declares it (``robot_inputs.PARAMETERS``), its
    description saying what it does ``here``."""
    spec = next(spec for spec in robot_inputs.PARAMETERS if spec.name == name)
    return dataclasses.replace(spec, description=f'{spec.description}; here {here}')


def camera_from_pose_frame_parameter() -> ParamSpec:
    """``camera_from_pose_frame`` for a node that takes the corrected trajectory without the
    pose stream (``map_node``): there only the default for keyframes whose posing
    ``multi_view_node`` did not say (nodes/posing.py)."""
    here = 'only for keyframes multi_view_node said no posing for (depth_fusion/posing/*)'
    return _robot_input_parameter('camera_from_pose_frame', here)


def pose_inverted_parameter() -> ParamSpec:
    """``pose_inverted`` for ``map_node``: the corrected trajectory is of the same pose source,
    inverted alike."""
    return _robot_input_parameter('pose_inverted', 'for the corrected trajectory')


def correction_limits(params: Mapping[str, Any]) -> CorrectionLimits:
    """The limits a node's declared parameters give."""
    return CorrectionLimits(
        float(params['correction_min_translation']),
        float(params['correction_min_rotation_deg']),
        float(params['correction_max_gap']),
    )


def path_poses(msg: Any) -> tuple[np.ndarray, np.ndarray, int]:
    """Stamps (ns, int64), poses (P, 4, 4) as they are, and the number of unusable poses of a
    ``nav_msgs/Path`` (the corrected trajectory, multi_view_node's ``reposed_keyframes``)."""
    stamps, poses, bad = [], [], 0
    for stamped in msg.poses:
        try:
            poses.append(pose_from_message(stamped))
        except InputError:
            bad += 1
            continue
        stamps.append(messages.stamp_to_ns(stamped.header.stamp))
    return np.asarray(stamps, np.int64), np.asarray(poses, np.float64).reshape(-1, 4, 4), bad


def path_from_message(
    msg: Any, T_pose_cam: np.ndarray, inverted: bool = False
) -> tuple[np.ndarray, np.ndarray, int]:
    """Stamps (s), camera-to-world poses (P, 4, 4) and the number of unusable poses of a Path.

    Its poses are of the pose stream's frame, as on ``camera/pose``: inverted first where
    those are (``pose_inverted``), then ``T_pose_cam`` (``camera_from_pose_frame``) makes them
    the optical frame's, as the keyframe poses are.
    (The correction ``T_new T_old^-1`` is the same whichever frame both are of, but ours are
    the camera's, so the path's must be too.)"""
    stamps_ns, poses, bad = path_poses(msg)
    seconds = np.array([messages.ns_to_sec(s) for s in stamps_ns.tolist()], np.float64)
    if inverted:
        poses = np.linalg.inv(poses)
    return seconds, poses @ T_pose_cam, bad


def read_path(
    stats: Any, msg: Any, T_pose_cam: np.ndarray, world_frame: str, inverted: bool = False
) -> tuple[np.ndarray, np.ndarray] | None:
    """A corrected trajectory as a node takes it: received counted, unusable poses dropped
    (``bad_pose``, the rest used), a path in another frame than ``world_frame`` dropped
    (``frame_mismatch``; ``''``: not known yet, anything goes). ``None``: nothing to use."""
    stats.received('corrected_path')
    stamps, poses, bad = path_from_message(msg, T_pose_cam, inverted)
    if bad:
        stats.dropped('bad_pose', f'corrected trajectory: {bad} of {len(msg.poses)} poses unusable')
    frame = msg.header.frame_id
    if frame and world_frame and frame != world_frame:
        stats.dropped('frame_mismatch', f'corrected trajectory in {frame!r}, poses in {world_frame!r}')
        return None
    return (stamps, poses) if len(stamps) else None
