"""Synthetic posed RGB-D sequences with exact depth and poses (the project's own test data).

A seeded indoor room (floor, walls, ceiling, boxes, tables; textured and texture-less
materials) is ray cast in numpy along a camera trajectory with high or low parallax::

    cfg = SynthConfig(width=320, height=240, frames=24, parallax='high', seed=3)
    seq = render_sequence(cfg)                      # in memory, depth GT at cfg resolution
    write_synthetic_sequence('artifacts/room', cfg)  # TUM folder (writer.py)

Determinism: everything derives from ``cfg.seed`` through separate random streams (room
and furniture; trajectory; per-frame sensor noise, pose jitter and exposure gain), so the
same config gives bit-identical output, the room does not depend on ``parallax`` or
``frames`` (a high- and a low-parallax sequence of one seed see the same room), and frame
``i``'s noise does not depend on how many frames were rendered before it.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from ...geometry import BODY_TO_OPTICAL
from ...progress import progress
from ..sequence import Frame, Sequence
from .config import PARALLAX_MODES, SynthConfig
from .motions import MOTION_FUNCTIONS
from .render import RenderedFrame, render_frame
from .scene import Scene, build_scene
from .shake import shaken_poses
from .trajectory import Trajectory, make_trajectory
from .walkers import scene_at

log = logging.getLogger(__name__)

#: Random-stream ids under the seed (numpy SeedSequence entropy ``[seed, stream, ...]``).
_ROOM_STREAM, _TRAJECTORY_STREAM, _NOISE_STREAM, _POSE_NOISE_STREAM, _GAIN_STREAM, _SHAKE_STREAM = range(6)
#: Poses per trajectory used to keep furniture off the camera path (independent of frames).
_KEEP_OUT_SAMPLES = 64
#: Sub-stream of the trajectory stream drawn by the stress motions.
_STRESS_SUBSTREAM = 1


def sequence_name(cfg: SynthConfig) -> str:
    name = f'synth_s{cfg.seed}_{cfg.parallax if cfg.motion == "parallax" else cfg.motion}'
    if cfg.focal_error:
        name += f'_focal{cfg.focal_error:+g}'
    if cfg.lens_k1:
        name += f'_lensk1{cfg.lens_k1:+g}'
    if cfg.pose_noise_m or cfg.pose_noise_deg:
        name += f'_posenoise{cfg.pose_noise_m * 1000:g}mm{cfg.pose_noise_deg:g}deg'
    if cfg.mount_tilt_deg:
        name += f'_tilt{cfg.mount_tilt_deg:+g}deg'
    if cfg.pose_frame != 'optical':
        name += f'_{cfg.pose_frame}poses'
    if cfg.pose_scale != 1.0:
        name += f'_posescale{cfg.pose_scale:g}'
    if cfg.pose_time_offset:
        name += f'_timeoffset{cfg.pose_time_offset * 1000:+g}ms'
    if cfg.exposure_time:
        name += f'_blur{cfg.exposure_time * 1000:.3g}ms'
    if cfg.readout_time:
        name += f'_rs{cfg.readout_time * 1000:.3g}ms'
    if cfg.gain_sigma:
        name += f'_gain{cfg.gain_sigma:g}'
    if cfg.walkers:
        name += f'_walkers{cfg.walkers}'
    if cfg.texture_period:
        name += f'_period{cfg.texture_period * 100:g}cm'
    if cfg.shake_m or cfg.shake_deg:
        name += f'_shake{cfg.shake_m * 1000:g}mm{cfg.shake_deg:g}deg'
    return name


def shifted_poses(poses: np.ndarray, frames: float) -> np.ndarray:
    """Each pose moved ``frames`` frame periods along the trajectory (``|frames| <= 1``), at the
    constant velocity of its step to the next frame (to the previous one for the last frame
    or a negative shift): translation and rotation vector scaled linearly.

    What a time offset between camera and pose source does to the poses a pipeline is told:
    every pose is where the camera was a little earlier or later, off along the motion.
    Inside the path this is ``geometry.interpolate_poses`` at the shifted stamps (linear
    translation, slerp; tested); it is written as one step scaling because the end frame
    needs the same motion extrapolated, which ``interpolate_poses`` refuses on purpose.
    """
    from scipy.spatial.transform import Rotation

    out = np.array(poses, dtype=np.float64, copy=True)
    n = len(out)
    if n < 2 or frames == 0.0:
        return out
    step = 1 if frames > 0 else -1
    nxt = np.clip(np.arange(n) + step, 0, n - 1)
    nxt[nxt == np.arange(n)] -= step  # the end of the path: the step from the other side, reversed
    sign = np.where(nxt - np.arange(n) == step, 1.0, -1.0)
    rel = np.linalg.inv(out) @ out[nxt]  # T_i^-1 T_j: the step in the camera frame
    f = abs(frames) * sign
    rot = Rotation.from_rotvec(Rotation.from_matrix(rel[:, :3, :3]).as_rotvec() * f[:, None]).as_matrix()
    move = np.repeat(np.eye(4)[None], n, axis=0)
    move[:, :3, :3] = rot
    move[:, :3, 3] = rel[:, :3, 3] * f[:, None]
    return out @ move


def told_poses(cfg: SynthConfig, poses: np.ndarray) -> np.ndarray:
    """The camera-to-world poses the pipeline is given: the true ones moved by the config's time
    offset (``pose_time_offset``, :func:`shifted_poses`) and turned by its mount tilt
    (``mount_tilt_deg``, about the camera's x axis), as a body frame's (``pose_frame``),
    with its per-frame jitter, and, for ``pose_frame`` 'inverted', inverted
    (``pose_noise_m``, ``pose_noise_deg``); a copy of the true ones without either.

    Each frame draws a translation offset (isotropic Gaussian) and a rotation about a random
    axis by a Gaussian angle, from its own random stream, so frame ``i``'s jitter does not
    depend on how many frames there are.
    """
    from scipy.spatial.transform import Rotation

    out = shifted_poses(poses, cfg.pose_time_offset * cfg.fps)
    if cfg.mount_tilt_deg:
        out[:, :3, :3] = (
            out[:, :3, :3] @ Rotation.from_rotvec([np.deg2rad(cfg.mount_tilt_deg), 0.0, 0.0]).as_matrix()
        )
    if cfg.pose_frame == 'body':  # T_body = T_cam @ M^-1, the camera held with its optical axis forward
        out[:, :3, :3] = out[:, :3, :3] @ BODY_TO_OPTICAL.T
    if not (cfg.pose_noise_m or cfg.pose_noise_deg):
        return _as_given(cfg, out)
    rotvecs, offsets = np.empty((len(out), 3)), np.empty((len(out), 3))
    for i in range(len(out)):  # one stream per frame; the draws only, the algebra is batched
        rng = np.random.default_rng([cfg.seed, _POSE_NOISE_STREAM, i])
        axis = rng.normal(size=3)
        rotvecs[i] = axis / max(np.linalg.norm(axis), 1e-12) * (np.deg2rad(cfg.pose_noise_deg) * rng.normal())
        offsets[i] = cfg.pose_noise_m * rng.normal(size=3)
    out[:, :3, :3] = out[:, :3, :3] @ Rotation.from_rotvec(rotvecs).as_matrix()
    out[:, :3, 3] += offsets
    return _as_given(cfg, out)


def _as_given(cfg: SynthConfig, poses: np.ndarray) -> np.ndarray:
    """The source's poses as it publishes them: positions in its unit (``pose_scale``), then
    inverted for ``pose_frame`` 'inverted' (the world's pose in the camera, T_cw, as a SLAM
    system keeps it)."""
    if cfg.pose_scale != 1.0:
        poses = poses.copy()
        poses[:, :3, 3] *= cfg.pose_scale
    return np.linalg.inv(poses) if cfg.pose_frame == 'inverted' else poses


def pose_source(cfg: SynthConfig, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the pose source records, ``(stamps, poses)``: each frame's pose (with its jitter),
    stamped ``pose_time_offset`` before the camera stamps the image it was taken with, as a
    pose source on a clock that runs behind the camera's does (or a camera that stamps late).
    Read at an image's stamp, such a stream gives the pose the camera had that much later:
    :func:`told_poses`, which it covers at every frame (the first or last frame's told pose
    is added at its own stamp where the shifted samples stop short of it). Re-read at the right
    offset, it gives the exact poses back, as a real pose source's samples would.
    """
    stamps = np.array([cfg.stamp(i) for i in range(cfg.frames)])
    told = told_poses(cfg, poses)
    offset = cfg.pose_time_offset
    if not offset:
        return stamps, told
    samples = told_poses(replace(cfg, pose_time_offset=0.0), poses)
    if offset > 0:
        return np.append(stamps - offset, stamps[-1]), np.concatenate([samples, told[-1:]])
    return np.insert(stamps - offset, 0, stamps[0]), np.concatenate([told[:1], samples])


def _view_offsets(cfg: SynthConfig) -> np.ndarray:
    """Times (in frame periods, from the stamp) of the ``blur_samples`` views a frame is made
    of: evenly over its exposure and readout together, centred on the stamp."""
    half = 0.5 * (cfg.exposure_time + cfg.readout_time) * cfg.fps  # at most one frame period
    return np.linspace(-half, half, cfg.blur_samples)


def exposure_poses(cfg: SynthConfig, poses: np.ndarray) -> np.ndarray | None:
    """(N, K, 4, 4): each frame's poses while its rows are exposed, ``cfg.blur_samples`` of
    them evenly over ``cfg.exposure_time`` and ``cfg.readout_time`` centred on its stamp, at
    the constant velocity of its step to the neighbouring frame (:func:`shifted_poses`);
    ``None`` without either (a sharp image of one instant)."""
    if not (cfg.exposure_time or cfg.readout_time):
        return None
    return np.stack([shifted_poses(poses, float(f)) for f in _view_offsets(cfg)], axis=1)


def rolling_shutter_weights(cfg: SynthConfig) -> np.ndarray | None:
    """(H, K) mix of the views of :func:`exposure_poses` for each image row, or ``None`` with a
    global shutter (every row the mean of the views).

    Row ``y`` is read at ``(y / (H - 1) - 1/2) * readout_time`` from the stamp and exposed
    around it. Its views are weighted by a tent centred at that time, as wide as the exposure
    (at least the spacing of the views, so a short exposure interpolates between the two
    nearest).
    """
    if not cfg.readout_time:
        return None
    offsets = _view_offsets(cfg)
    rows = (np.arange(cfg.height) / max(cfg.height - 1, 1) - 0.5) * cfg.readout_time * cfg.fps
    width = max(cfg.exposure_time * cfg.fps, float(offsets[1] - offsets[0]))
    weights = np.maximum(0.0, 1.0 - np.abs(offsets[None, :] - rows[:, None]) / width)
    return weights / weights.sum(axis=1, keepdims=True)


def frame_gain(cfg: SynthConfig, index: int) -> float:
    """Frame ``index``'s auto-exposure gain ``exp(gain_sigma * n)``, from its own random
    stream (so it does not depend on how many frames there are); 1 without ``gain_sigma``."""
    if not cfg.gain_sigma:
        return 1.0
    return float(np.exp(cfg.gain_sigma * np.random.default_rng([cfg.seed, _GAIN_STREAM, index]).normal()))


def build_world(cfg: SynthConfig) -> tuple[Scene, Trajectory]:
    """The seeded room and the camera trajectory of a config."""
    room_rng = np.random.default_rng([cfg.seed, _ROOM_STREAM])
    room = np.asarray(cfg.room_size, dtype=np.float64) * (1.0 + cfg.room_jitter * room_rng.uniform(-1, 1, 3))

    def trajectory(parallax: str, frames: int) -> Trajectory:
        rng = np.random.default_rng([cfg.seed, _TRAJECTORY_STREAM])
        return make_trajectory(parallax, frames, room, rng, cfg.sweep)

    # Furniture keeps clear of both parallax modes' paths, so the room is the same for both.
    both = [trajectory(mode, _KEEP_OUT_SAMPLES) for mode in PARALLAX_MODES]
    main = trajectory(cfg.parallax, cfg.frames)
    paths = [t.poses for t in both]
    if cfg.motion != 'parallax':
        # A stress motion starts from the same nominal viewpoint; furniture keeps off it too.
        rng = np.random.default_rng([cfg.seed, _TRAJECTORY_STREAM, _STRESS_SUBSTREAM])
        motion = MOTION_FUNCTIONS[cfg.motion]
        main = motion(
            cfg.frames,
            room,
            main.view_origin,
            main.view_target,
            rng,
            cfg.step_translation,
            cfg.step_rotation_deg,
        )
        paths.append(main.poses)
    keep_out = Trajectory(np.concatenate(paths), both[0].view_origin, both[0].view_target)
    scene = build_scene(cfg, room, keep_out, room_rng)
    if cfg.shake_m or cfg.shake_deg:  # a few mm off the path the furniture keeps clear of
        rng = np.random.default_rng([cfg.seed, _SHAKE_STREAM])
        main = replace(main, poses=shaken_poses(main.poses, cfg.fps, cfg.shake_m, cfg.shake_deg, rng))
    return scene, main


def iter_frames(
    cfg: SynthConfig,
    scene: Scene | None = None,
    trajectory: Trajectory | None = None,
    show_progress: bool = False,
) -> Iterator[tuple[int, RenderedFrame, np.ndarray]]:
    """Yield ``(index, rendered frame, T_wc)`` for every frame of the config, lazily; ``T_wc`` is
    the pose the pipeline is told (:func:`told_poses`), the frame is rendered at the true one."""
    if scene is None or trajectory is None:
        scene, trajectory = build_world(cfg)
    camera = cfg.camera()
    told = told_poses(cfg, trajectory.poses)
    exposures = exposure_poses(cfg, trajectory.poses)
    row_weights = rolling_shutter_weights(cfg)
    for i in progress(range(cfg.frames), desc='render', unit='frame', disable=not show_progress):
        rng = np.random.default_rng([cfg.seed, _NOISE_STREAM, i])
        frame = render_frame(
            scene_at(scene, cfg, trajectory, i),
            camera,
            trajectory.poses[i],
            noise_sigma=cfg.noise_sigma,
            rng=rng,
            antialias=cfg.antialias,
            gain=frame_gain(cfg, i),
            exposure_poses=None if exposures is None else exposures[i],
            row_weights=row_weights,
            lens_k1=cfg.lens_k1,
        )
        if cfg.pose_scale != 1.0:  # the ground truth in the poses' unit, as they are
            frame = replace(frame, depth=frame.depth * np.float32(cfg.pose_scale))
        yield i, frame, told[i]


def render_sequence(cfg: SynthConfig, show_progress: bool = False, max_frames: int | None = None) -> Sequence:
    """Render the whole sequence in memory (its first ``max_frames`` only, when given: the start of
    a longer stream, whose motion follows ``cfg.frames``).

    rgb and ground-truth depth (float32 z-depth in metres, exact at pixel centres, no invalid
    pixels) share the config's size. ``gt_camera`` is the true camera; ``camera`` is what the
    pipeline is told (the same unless ``focal_error``); frame poses are the ones the pipeline is
    told (the true ones unless ``pose_noise_m`` / ``pose_noise_deg``); ``pose_stream`` is the
    pose source's own record (:func:`pose_source`).
    """
    scene, trajectory = build_world(cfg)
    rendered = iter_frames(cfg, scene, trajectory, show_progress=show_progress)
    frames = [
        Frame(index=i, stamp=cfg.stamp(i), rgb=f.rgb, pose=pose.copy(), depth=f.depth)
        for i, f, pose in itertools.islice(rendered, max_frames)
    ]
    return Sequence(
        name=sequence_name(cfg),
        camera=cfg.pipeline_camera(),
        frames=frames,
        gt_camera=cfg.camera(),
        pose_stream=pose_source(cfg, trajectory.poses),
    )
