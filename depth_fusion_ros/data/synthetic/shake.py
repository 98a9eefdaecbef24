"""Hand shake: the small, fast, uneven motion a hand-held camera adds to any path.

Why: the synthetic paths are smooth (constant speed, slow wobbles), so two frames a moment
apart move the same way whenever they are taken, and a time offset between the camera and
the pose source changes no relative pose. A hand changes speed and turn rate every few
hundred milliseconds (TUM fr1 turns at up to 40 deg/s and reverses), and that is what makes a
time offset both harmful to the depth and observable in the images.

Each of the three rotation and three translation axes of the camera gets a sum of three
sinusoids between 1 and 4 Hz (hand tremor and walking sway) with seeded phases, scaled to the
given standard deviation, as a function of time (``index / fps``), so the shake of a frame
does not depend on how many frames there are.
"""

from __future__ import annotations

import numpy as np

#: Frequencies (Hz) the shake is drawn from, and how many sinusoids each axis sums.
_BAND = (1.0, 4.0)
_TONES = 3


def shake_offsets(rng: np.random.Generator, times: np.ndarray, std: float) -> np.ndarray:
    """(N, 3) smooth offsets at ``times`` (s), each column with standard deviation ``std``."""
    freqs = rng.uniform(*_BAND, size=(3, _TONES))
    phases = rng.uniform(0.0, 2 * np.pi, size=(3, _TONES))
    waves = np.sin(2 * np.pi * freqs[None] * times[:, None, None] + phases[None])  # (N, 3, tones)
    # A sum of ``_TONES`` unit sinusoids has a standard deviation of sqrt(tones / 2).
    return std * waves.sum(axis=2) / np.sqrt(_TONES / 2)


def shaken_poses(
    poses: np.ndarray, fps: float, shake_m: float, shake_deg: float, rng: np.random.Generator
) -> np.ndarray:
    """``poses`` (N, 4, 4, camera-to-world) with a hand's shake added in the camera frame."""
    from scipy.spatial.transform import Rotation

    times = np.arange(len(poses)) / fps
    move = np.repeat(np.eye(4)[None], len(poses), axis=0)
    move[:, :3, :3] = Rotation.from_rotvec(np.deg2rad(shake_offsets(rng, times, shake_deg))).as_matrix()
    move[:, :3, 3] = shake_offsets(rng, times, shake_m)
    return np.asarray(poses, dtype=np.float64) @ move
