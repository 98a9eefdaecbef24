"""The two parameters of the pose-jump test (:mod:`..pose_jumps`), declared alike by every
node that makes it (``multi_view_node`` on its pose stream, ``map_node`` on keyframe poses):
one spelling and one range, each node saying what a jump makes it do."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..pose_jumps import PoseJumpLimits
from .params import ParamSpec


def pose_jump_parameters(what: str, consequence: str) -> tuple[ParamSpec, ParamSpec]:
    """``max_pose_speed`` and ``max_pose_angular_speed`` for ``what`` (e.g. ``'poses'``),
    whose jump has ``consequence`` (said in the description)."""
    return (
        ParamSpec(
            'max_pose_speed',
            PoseJumpLimits.max_speed,
            f'm/s: two consecutive {what} further apart than this speed allows (plus 2 cm of pose noise) '
            f'are a jump (the pose source relocalised or closed a loop): {consequence} (0: off)',
            0.0,
        ),
        ParamSpec(
            'max_pose_angular_speed',
            PoseJumpLimits.max_angular_speed_deg,
            f'degrees per second: two consecutive {what} turned further apart than this allows (plus 2 '
            'degrees) are a jump, as max_pose_speed (0: off)',
            0.0,
        ),
    )


def pose_jump_limits(params: Mapping[str, Any]) -> PoseJumpLimits:
    """The limits a node's declared parameters give."""
    return PoseJumpLimits(float(params['max_pose_speed']), float(params['max_pose_angular_speed']))
