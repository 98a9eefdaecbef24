"""Camera trajectories of the synthetic sequences, with controllable parallax.

The world frame is z-up with the room spanning ``[-W/2, W/2] x [-D/2, D/2] x [0, H]``; the
camera stands near the ``y = -D/2`` wall and looks roughly along ``+y`` into the room where
the furniture is. Two regimes matter to the project:

* ``high`` parallax: a lateral sweep (0.6-1.2 m) with a gentle look-at, the regime where
  multi-view stereo is accurate;
* ``low`` parallax: panning and tilting from nearly one spot (a few cm of translation),
  where multi-view depth is unreliable and the fusion must lean on the single view.

Poses are camera-to-world 4x4 (optical frame: x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Camera keeps at least this distance from side/back walls (m).
WALL_CLEARANCE = 0.5


@dataclass(frozen=True)
class Trajectory:
    """Poses plus where the camera looks, which the furniture layout uses."""

    poses: np.ndarray  # (N, 4, 4) camera-to-world
    view_origin: np.ndarray  # (3,) nominal camera position (the same for both parallax modes)
    view_target: np.ndarray  # (3,) nominal look-at point (furniture is placed around it)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


def look_at(position: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose at ``position`` looking at ``target`` with z-up world, optical
    axes x right, y down, z forward, and an extra ``roll`` (radians) about the view axis."""
    forward = np.asarray(target, dtype=np.float64) - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    norm = np.linalg.norm(right)
    if norm < 1e-6:
        raise ValueError('look_at: view direction is vertical, the camera roll is undefined')
    right /= norm
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, forward, position
    return T


def _wobble(rng: np.random.Generator, s: np.ndarray, amplitude: float) -> np.ndarray:
    """Smooth, seeded low-frequency perturbation (two sinusoids) of size ``amplitude``."""
    out = np.zeros_like(s)
    for cycles in (0.7, 1.6):
        out += amplitude / 2 * np.sin(2 * np.pi * (cycles * s + rng.uniform()))
    return out


def make_trajectory(
    parallax: str, frames: int, room: np.ndarray, rng: np.random.Generator, sweep: float | None = None
) -> Trajectory:
    """Seeded trajectory of ``frames`` poses in a room of size ``room`` = (W, D, H) metres.

    The trajectory spans the same path whatever the number of frames (more frames = denser
    sampling), so ``frames`` changes the inter-frame baseline, not where the camera goes.
    The nominal position and look-at point are drawn first, so the same ``rng`` state gives
    the same viewpoint for both parallax modes.
    """
    W, D = float(room[0]), float(room[1])
    s = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    base = np.array([rng.uniform(-0.15, 0.15) * W, -D / 2 + rng.uniform(0.55, 0.85), rng.uniform(1.25, 1.6)])
    # Look 2-2.8 m into the room, but not through the far wall of a small room.
    view_dist = max(min(rng.uniform(2.0, 2.8), D - (base[1] + D / 2) - 0.4), 0.5)
    target = np.array([base[0] + rng.uniform(-0.3, 0.3), base[1] + view_dist, rng.uniform(0.45, 0.85)])
    roll = _wobble(rng, s, np.deg2rad(2.0))
    if parallax == 'high':
        length = sweep if sweep is not None else rng.uniform(0.6, 1.2)
        half_room = W / 2 - WALL_CLEARANCE
        length = min(length, 2 * half_room)
        direction = rng.choice((-1.0, 1.0))
        centre_x = float(np.clip(base[0], -half_room + length / 2, half_room - length / 2))
        x = centre_x + direction * length * (s - 0.5)
        positions = np.stack((x, base[1] + _wobble(rng, s, 0.06), base[2] + _wobble(rng, s, 0.05)), axis=1)
        # Gentle look-at: the target follows the camera by half its offset, so the view
        # rotates only a few degrees while the baseline grows.
        targets = np.tile(target, (frames, 1))
        targets[:, 0] = target[0] + 0.5 * (x - centre_x)
        targets[:, 2] += _wobble(rng, s, 0.1)
    else:
        yaw_amp = np.deg2rad(rng.uniform(10.0, 18.0)) * rng.choice((-1.0, 1.0))
        tilt_amp = np.deg2rad(rng.uniform(2.0, 5.0))
        yaw = yaw_amp * (2 * s - 1)
        tilt = tilt_amp * np.sin(2 * np.pi * (s + rng.uniform()))
        shift = rng.uniform(0.02, 0.04)
        positions = np.stack(
            (
                base[0] + _wobble(rng, s, 0.02),
                base[1] + shift * s,
                base[2] + _wobble(rng, s, 0.01),
            ),
            axis=1,
        )
        rel = target - base
        dist_h = np.hypot(rel[0], rel[1])
        heading = np.arctan2(rel[1], rel[0]) - yaw
        pitch = np.arctan2(rel[2], dist_h) + tilt
        directions = np.stack(
            (np.cos(heading) * np.cos(pitch), np.sin(heading) * np.cos(pitch), np.sin(pitch)), axis=1
        )
        targets = positions + directions * view_dist
    poses = np.stack([look_at(p, t, r) for p, t, r in zip(positions, targets, roll, strict=True)])
    return Trajectory(poses, base, target)
