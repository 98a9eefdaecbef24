"""Pose jumps: a pose source that moves the camera faster than a camera moves.

A SLAM system that relocalises, closes a loop or resets its map moves its pose estimate by
decimetres between two messages a frame apart. Relative poses across that step are wrong by
the correction: a frame from before it, chosen as a neighbour of a keyframe after it, or a
filter estimate propagated across it, sits in another world. The multi-view depth is then
consistently wrong, which no later check can tell from a right one (the points agree with
each other), so the fusion would trust it. The pose stream itself shows the step: an implied
speed far above anything the camera does. Nothing is lost by starting over there; the
estimates before the step are only valid in the world they were made in.

The test is by speed, with a slack for pose noise over short intervals (a 200 Hz VIO's
poses 5 ms apart still jitter by millimetres). No ROS import: stamps are float seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import invert_pose, rotation_angle


@dataclass(frozen=True)
class PoseJumpLimits:
    """How fast the camera may move between two consecutive poses before it is a jump.

    The defaults allow a running person, a car park robot or a slow drone (5 m/s, 360 deg/s)
    and catch a relocalisation of 20 cm or more between two poses 33 ms apart. 0 turns a
    limit off; both 0 turns the test off.
    """

    #: Largest believable speed (m/s) of the camera between two poses.
    max_speed: float = 5.0
    #: Largest believable rotation rate (degrees per second) between two poses.
    max_angular_speed_deg: float = 360.0
    #: Translation (m) always allowed between two poses, however close in time: pose noise.
    slack_m: float = 0.02
    #: Rotation (degrees) always allowed between two poses, however close in time.
    slack_deg: float = 2.0

    def __post_init__(self) -> None:
        for name in ('max_speed', 'max_angular_speed_deg', 'slack_m', 'slack_deg'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value}')

    @property
    def enabled(self) -> bool:
        return self.max_speed > 0 or self.max_angular_speed_deg > 0


@dataclass(frozen=True)
class PoseJump:
    """A step between the poses at ``before`` and ``after`` (s) that no camera makes."""

    before: float
    after: float
    distance_m: float
    angle_deg: float

    def describe(self, limits: PoseJumpLimits) -> str:
        """``'0.42 m and 3.1 deg in 0.033 s (limits 5 m/s, 360 deg/s)'``."""
        dt = self.after - self.before
        return (
            f'{self.distance_m:.2f} m and {self.angle_deg:.1f} deg in {dt:.3f} s '
            f'(limits {limits.max_speed:g} m/s, {limits.max_angular_speed_deg:g} deg/s)'
        )


def find_jump(
    limits: PoseJumpLimits, t0: float, T0: np.ndarray, t1: float, T1: np.ndarray
) -> PoseJump | None:
    """The jump between the camera-to-world poses ``T0`` at ``t0`` and ``T1`` at ``t1`` (any
    order), or ``None`` when the step is within the limits (or the limits are off)."""
    if not limits.enabled:
        return None
    if t1 < t0:
        t0, T0, t1, T1 = t1, T1, t0, T0
    dt = t1 - t0
    step = invert_pose(T0) @ T1
    distance = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    angle = math.degrees(rotation_angle(step[:3, :3]))
    too_far = limits.max_speed > 0 and distance > limits.max_speed * dt + limits.slack_m
    too_turned = (
        limits.max_angular_speed_deg > 0 and angle > limits.max_angular_speed_deg * dt + limits.slack_deg
    )
    if too_far or too_turned:
        return PoseJump(t0, t1, distance, angle)
    return None
