"""Named stress cases: synthetic sequences that reproduce where multi-view depth misleads the fusion.

Each case is a ``SynthConfig`` preset (any field can still be overridden). They mirror
the failures reported on real sequences (issue 11), so the fusion's guard can be tested on
data with exact ground truth:

=================  ==========================================================================
``translation``    the good case: a lateral sweep with high parallax (multi-view is reliable)
``rotation``       hand-held, rotation-dominant sweep: 1.2 cm and 0.6 deg per frame at 30 Hz
``keyframes``      a SLAM keyframe stream: 15 cm and 6.7 deg between frames 0.67 s apart
``low_texture``    most surfaces flat, the rest faint (texture contrast 0.25); lateral sweep
``wrong_focal``    the lateral sweep, but camera.yaml's focal lengths are 10 % too long
``pose_noise``     the lateral sweep, but every pose the pipeline is told has a jitter of 2 mm and
                   0.1 deg (std, independent per frame): a SLAM or odometry pose source
``forward``        a ground robot driving ahead, 1.5 cm per frame along the view (0.45 m/s at
                   30 Hz), heading wobbling by 2 deg: the epipole is in the image, and the
                   pixels around it see almost no parallax however far the robot drives
``motion_blur``    the lateral sweep walked fast (3 cm per frame, 0.9 m/s at 30 Hz) in a dim
                   room: the shutter is open for the whole frame period, so every image is
                   smeared by 2-4 px along the motion (hand-held TUM fr1 sequences look so)
``rolling_shutter`` the ``motion_blur`` walk (3 cm per frame) seen by a rolling shutter that
                   reads the rows out over 30 ms: the bottom row 2.7 cm further along the
                   path than the top one, a skew of 3-4 px
``auto_exposure``  the lateral sweep with an auto-exposure that changes every frame: each
                   image scaled by its own gain (log-gain std 0.15) and clipped at 255
``moving_object``  the lateral sweep with a person-sized box walking across the view at
                   1 m/s, 1.6 m ahead: a world that is not static
``repetitive``     the lateral sweep in a room of tiles: every textured surface repeats one
                   motif every 8 cm (10-18 px at 320x240), so an epipolar search meets the
                   same patch again every period (tiled floors, brick walls, shelves)
``time_offset``    the lateral sweep by a shaking hand (5 mm and 0.5 deg per axis, 1-4 Hz),
                   told by a pose source 20 ms ahead of the camera's stamps: each told pose
                   is where the camera was 0.6 frame later, off along a motion that keeps
                   changing (``multiview/time_offset_check.py`` finds it)
``mount_tilt``     the ``forward`` robot with its camera mounted 2 deg more tilted than the
                   pose frame it is told (``T_told = T_true @ R_x(2 deg)``): the epipole is
                   told 9 px off at 320x240 (``multiview/mount_check.py`` finds it)
``large_hall``     a robot driving ahead at 1 m/s (3.3 cm per frame at 30 Hz) through a hall of
                   14 x 12 x 4.5 m (a warehouse, a lobby): half the view is 3 m and more away
                   and a tenth beyond 10 m, past the multi-view depth range, where a pixel's
                   parallax is a fraction of a pixel; the single-view error grows with depth
``handheld``       the ``rotation`` sweep by a phone-like camera, everything a little off at
                   once: camera_info's focal length 5 % long, a rolling shutter (20 ms), 15 ms
                   exposures, an auto-exposure (log-gain std 0.1), sensor noise 4 grey levels,
                   poses jittered by 2 mm and 0.1 deg and 10 ms ahead. Each alone is harmless
                   here; together they leave the focal check unable to tell (``unobservable``),
                   and the told focal length biases every rotation-dominant depth the same way
                   (``multiview/focal_bias.py``)
``lens_distortion`` the ``rotation`` sweep through a lens with barrel distortion (plumb_bob
                   k1 = -0.1: 4 % at the image corners, 11 px at 320x240) that camera_info
                   does not hold (zero distortion): a camera used uncalibrated, or its
                   images not rectified. Undone with a pinhole model, the told rotation
                   leaves each point a shift that grows with its distance from the centre
=================  ==========================================================================

``stress_config('rotation', width=160, height=120, frames=30)`` gives a small version for
tests; ``depth-fusion synth OUT --stress rotation`` writes one as a TUM folder.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from .config import SynthConfig

STRESS_CASES: dict[str, dict[str, Any]] = {
    'translation': {'parallax': 'high', 'sweep': 1.0},
    'rotation': {'motion': 'rotation_sweep', 'step_translation': 0.012, 'step_rotation_deg': 0.6},
    'keyframes': {
        'motion': 'keyframe_stream',
        'step_translation': 0.15,
        'step_rotation_deg': 6.7,
        'fps': 1.5,
    },
    'low_texture': {'parallax': 'high', 'sweep': 1.0, 'textureless_fraction': 0.85, 'texture_contrast': 0.25},
    'wrong_focal': {'parallax': 'high', 'sweep': 1.0, 'focal_error': 0.10},
    'pose_noise': {'parallax': 'high', 'sweep': 1.0, 'pose_noise_m': 0.002, 'pose_noise_deg': 0.1},
    'forward': {'motion': 'forward', 'step_translation': 0.015, 'step_rotation_deg': 0.2},
    'motion_blur': {'parallax': 'high', 'sweep': 3.0, 'exposure_time': 1.0 / 30.0},
    'rolling_shutter': {'parallax': 'high', 'sweep': 3.0, 'readout_time': 0.03},
    'auto_exposure': {'parallax': 'high', 'sweep': 1.0, 'gain_sigma': 0.15},
    'moving_object': {'parallax': 'high', 'sweep': 1.0, 'walkers': 1},
    'repetitive': {'parallax': 'high', 'sweep': 1.0, 'texture_period': 0.08},
    'mount_tilt': {
        'motion': 'forward',
        'step_translation': 0.015,
        'step_rotation_deg': 0.2,
        'mount_tilt_deg': 2.0,
    },
    'large_hall': {
        'motion': 'forward',
        'step_translation': 0.033,
        'step_rotation_deg': 0.3,
        'room_size': (14.0, 12.0, 4.5),
    },
    'time_offset': {
        'parallax': 'high',
        'sweep': 1.0,
        'shake_m': 0.005,
        'shake_deg': 0.5,
        'pose_time_offset': 0.02,
    },
    'handheld': {
        'motion': 'rotation_sweep',
        'step_translation': 0.012,
        'step_rotation_deg': 0.6,
        'focal_error': 0.05,
        'readout_time': 0.02,
        'exposure_time': 0.015,
        'gain_sigma': 0.1,
        'noise_sigma': 4.0,
        'pose_noise_m': 0.002,
        'pose_noise_deg': 0.1,
        'pose_time_offset': 0.01,
    },
    'lens_distortion': {
        'motion': 'rotation_sweep',
        'step_translation': 0.012,
        'step_rotation_deg': 0.6,
        'lens_k1': -0.1,
    },
}


def stress_config(name: str, **overrides: Any) -> SynthConfig:
    """The ``SynthConfig`` of a named stress case (``STRESS_CASES``), with ``overrides``."""
    if name not in STRESS_CASES:
        raise ValueError(f'unknown stress case {name!r}; expected one of {", ".join(STRESS_CASES)}')
    base = SynthConfig(width=320, height=240, frames=100)
    return replace(base, **{**STRESS_CASES[name], **overrides})
