"""Stress camera motions: hand-held, keyframe-stream and driving regimes hard for multi-view depth.

All are parametrised by the translation and rotation *between consecutive frames*
(``SynthConfig.step_translation``, ``step_rotation_deg``), because that is what a user
reports and what decides the multi-view geometry:

* ``rotation_sweep`` — a hand-held sweep of a room, e.g. 1.2 cm and 0.6 deg per frame at
  30 Hz: the camera walks sideways *and turns the same way*, so the image motion is mostly
  rotation (0.6 deg is ~3 px at 320x240, the translation ~1.5 px at 2 m). Over 100 frames it
  turns ~60 deg and moves ~1.2 m. Neighbours with enough baseline are also rotated a lot.
* ``keyframe_stream`` — what a SLAM's keyframes give: e.g. 15 cm and 6.7 deg between
  consecutive frames (0.67 s apart). The camera orbits a point in front of it (a radius
  that makes the two steps consistent: ``R = step / angle``) back and forth over +-5 steps,
  so every neighbour is at least one wide step away.
* ``forward`` — a ground robot driving ahead (e.g. 1.5 cm per frame at 30 Hz) with a slight
  heading wobble: the epipole lies in the image, so the pixels around it see almost no
  parallax however far it drives.

Poses are camera-to-world (optical frame: x right, y down, z forward), in the room frame of
``trajectory.py`` (z up, camera near the ``y = -D/2`` wall looking along ``+y``).
"""

from __future__ import annotations

import numpy as np

from .trajectory import WALL_CLEARANCE, Trajectory, look_at

#: Half-period (in frames) of the keyframe stream's back-and-forth orbit.
STREAM_HALF_PERIOD = 5


def _triangle(k: np.ndarray, half_period: int) -> np.ndarray:
    """Integer triangle wave 0, 1, ..., h, h-1, ..., -h, ... centred on 0 (amplitude h), one
    step a frame. (Until 2026-11-30 it rose to h // 2 + 1 and then jumped 2h + 1 steps back, so
    the ``keyframes`` stress stream turned 60 deg between two frames every 4h frames.)"""
    h = int(half_period)
    return h - np.abs((np.asarray(k) + h) % (4 * h) - 2 * h)


def _level_ahead(base: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Unit vector of the nominal view from ``base`` to ``target`` in the floor plane."""
    ahead = target - base
    ahead[2] = 0.0
    return ahead / np.linalg.norm(ahead)


def _headed_poses(
    positions: np.ndarray, heading: np.ndarray, base: np.ndarray, target: np.ndarray
) -> np.ndarray:
    """Camera-to-world poses at ``positions`` looking along ``heading`` (radians, per frame,
    about the room's z axis), pitched as the nominal view from ``base`` to ``target``."""
    rel = target - base
    dist = float(np.linalg.norm(rel))
    pitch = np.arctan2(rel[2], np.hypot(rel[0], rel[1]))
    directions = np.stack(
        (
            np.cos(heading) * np.cos(pitch),
            np.sin(heading) * np.cos(pitch),
            np.full(len(heading), np.sin(pitch)),
        ),
        axis=1,
    )
    return np.stack([look_at(p, p + d * dist) for p, d in zip(positions, directions, strict=True)])


def rotation_sweep(
    frames: int,
    room: np.ndarray,
    base: np.ndarray,
    target: np.ndarray,
    rng: np.random.Generator,
    step: float,
    step_deg: float,
) -> Trajectory:
    """Sideways walk turning the same way: ``step`` m and ``step_deg`` deg per frame, centred
    on the nominal viewpoint (clipped to the room)."""
    half_room = float(room[0]) / 2 - WALL_CLEARANCE
    k = np.arange(frames, dtype=np.float64) - (frames - 1) / 2.0
    direction = float(rng.choice((-1.0, 1.0)))
    x = np.clip(base[0] + direction * step * k, -half_room, half_room)
    positions = np.stack((x, np.full(frames, base[1]), np.full(frames, base[2])), axis=1)
    positions[:, 2] += 0.01 * np.sin(2 * np.pi * (k / 90.0 + rng.uniform()))  # a slow bob, 3 s period
    rel = target - base
    # Moving towards +x and turning right (clockwise seen from above, heading decreasing):
    # translation and rotation then move the image the same way.
    heading = np.arctan2(rel[1], rel[0]) - direction * np.deg2rad(step_deg) * k
    return Trajectory(_headed_poses(positions, heading, base, target), base, target)


def keyframe_stream(
    frames: int,
    room: np.ndarray,
    base: np.ndarray,
    target: np.ndarray,
    rng: np.random.Generator,
    step: float,
    step_deg: float,
) -> Trajectory:
    """Back-and-forth orbit about a point ahead of the nominal camera: each frame ``step`` m
    and ``step_deg`` deg from the previous one."""
    angle_step = np.deg2rad(max(step_deg, 1e-3))
    radius = step / (2.0 * np.sin(angle_step / 2.0)) if step > 0 else 0.0
    centre = base + _level_ahead(base, target) * radius
    centre[2] = target[2]
    start = float(np.arctan2(base[1] - centre[1], base[0] - centre[0]))
    k = _triangle(np.arange(frames), STREAM_HALF_PERIOD) * float(rng.choice((-1.0, 1.0)))
    angles = start + angle_step * k
    positions = np.stack(
        (centre[0] + radius * np.cos(angles), centre[1] + radius * np.sin(angles), np.full(frames, base[2])),
        axis=1,
    )
    # Pure orbit: the view turns by exactly the orbit angle, looking at the centre's column.
    poses = np.stack([look_at(p, np.array([centre[0], centre[1], target[2]])) for p in positions])
    return Trajectory(poses, base, target)


def forward_drive(
    frames: int,
    room: np.ndarray,
    base: np.ndarray,
    target: np.ndarray,
    rng: np.random.Generator,
    step: float,
    step_deg: float,
) -> Trajectory:
    """A ground robot driving ahead: ``step`` m per frame along the viewing direction, so the
    epipole lies in the image and the pixels around it see almost no parallax; the heading
    wobbles by up to ``step_deg`` x 10 degrees (3 s period), a slightly steered drive."""
    k = np.arange(frames, dtype=np.float64)
    ahead = _level_ahead(base, target)
    positions = base[None, :] + (step * k)[:, None] * ahead[None, :]
    heading0 = float(np.arctan2(ahead[1], ahead[0]))
    heading = heading0 + np.deg2rad(10.0 * step_deg) * np.sin(2 * np.pi * (k / 90.0 + rng.uniform()))
    return Trajectory(_headed_poses(positions, heading, base, target), base, target)


MOTION_FUNCTIONS = {
    'rotation_sweep': rotation_sweep,
    'keyframe_stream': keyframe_stream,
    'forward': forward_drive,
}
