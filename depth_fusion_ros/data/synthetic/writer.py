"""Write a synthetic sequence as a TUM-layout folder with a SOURCE.md that regenerates it."""

from __future__ import annotations

import itertools
import shlex
from pathlib import Path

import numpy as np
import yaml

from ..tum_writer import check_replaceable, write_tum_folder
from .config import SynthConfig
from .world import build_world, iter_frames, pose_source, sequence_name


def _motion(cfg: SynthConfig) -> str:
    if cfg.motion == 'parallax':
        return f'with {cfg.parallax} parallax'
    return f'{cfg.motion} ({cfg.step_translation:g} m and {cfg.step_rotation_deg:g} deg per frame)'


def _calibration_note(cfg: SynthConfig) -> str:
    """What camera.yaml deliberately gets wrong: its focal lengths, the lens it leaves out."""
    note = ''
    if cfg.focal_error:
        note += (
            f'\n**camera.yaml is deliberately wrong**: its focal lengths are {cfg.focal_error:+.0%} off the '
            f'ones used for rendering (fx = {cfg.camera().fx:g} px), a calibration-error stress case.'
        )
    if cfg.lens_k1:
        note += (
            f'\n**The lens distorts and camera.yaml does not say so**: images and depth are rendered '
            f'through a radial distortion k1 = {cfg.lens_k1:g} (plumb_bob), camera.yaml has none, a '
            'calibration-error stress case.'
        )
    return note


def _pose_note(cfg: SynthConfig) -> str:
    note = ''
    if cfg.pose_noise_m or cfg.pose_noise_deg:
        note += (
            f'\n**groundtruth.txt is deliberately noisy**: every pose has an independent jitter of '
            f'{cfg.pose_noise_m * 1000:g} mm and {cfg.pose_noise_deg:g} deg (std) against the poses used '
            'for rendering, a pose-source-noise stress case; the depth images stay exact.'
        )
    if cfg.pose_time_offset:
        note += (
            f"\n**groundtruth.txt is deliberately out of sync**: every pose is the camera's pose at a "
            f"frame, stamped {cfg.pose_time_offset * 1000:+g} ms before that frame's image, so read at an "
            f"image's stamp it is the camera's pose {cfg.pose_time_offset * 1000:+g} ms later (a camera / "
            'pose-source time offset stress case); the depth images stay exact.'
        )
    if cfg.pose_frame == 'body':
        note += (
            "\n**groundtruth.txt holds a body frame's poses**: every pose is that of a REP 103 body "
            'frame (x forward, y left, z up) holding the camera with its optical axis forward, not '
            "the camera's optical frame; camera_from_pose_frame [0, 0, 0, -0.5, 0.5, -0.5, 0.5] turns "
            'them back (a pose-frame stress case); the depth images stay exact.'
        )
    if cfg.pose_frame == 'inverted':
        note += (
            "\n**groundtruth.txt holds inverted poses**: every pose is the world's pose in the camera "
            "(T_cw), not the camera's in the world (T_wc) that the TUM format and ROS mean; "
            'pose_inverted: true reads them right (a pose-convention stress case); the depth images '
            'stay exact.'
        )
    if cfg.pose_scale != 1.0:
        note += (
            f'\n**Positions and depth are in a unit of {1 / cfg.pose_scale:.3g} m**: groundtruth.txt and '
            f'depth/*.png are the true ones times {cfg.pose_scale:g}, as a monocular SLAM gives them; the '
            'images are rendered in metres (a pose-unit stress case).'
        )
    if cfg.mount_tilt_deg:
        note += (
            f"\n**groundtruth.txt is deliberately turned**: every pose is the camera's turned by "
            f'{cfg.mount_tilt_deg:+g} deg about its x axis, a camera mounted tilted against the pose frame '
            'it is told (a mount rotation stress case); the depth images stay exact.'
        )
    return note


def _sensor_note(cfg: SynthConfig) -> str:
    note = ''
    if cfg.exposure_time:
        note += (
            f'\n**The images are motion-blurred**: each averages {cfg.blur_samples} views over a '
            f'{cfg.exposure_time * 1000:.3g} ms exposure centred on its stamp; depth and pose are those '
            'of the stamp.'
        )
    if cfg.readout_time:
        note += (
            '\n**The shutter rolls**: the rows are read out top to bottom over '
            f'{cfg.readout_time * 1000:.3g} ms centred on the stamp, each at its own pose; depth and pose '
            'are those of the stamp.'
        )
    if cfg.gain_sigma:
        note += (
            f'\n**The exposure changes from frame to frame**: each image is scaled by its own gain '
            f'exp({cfg.gain_sigma:g} n), n standard normal (an auto-exposure), and clipped at 255.'
        )
    if cfg.walkers:
        note += (
            f'\n**The world is not static**: {cfg.walkers} person-sized box(es) walk back and forth '
            f'across the view at {cfg.walker_speed:g} m/s; the depth images show them where they are.'
        )
    if cfg.texture_period:
        note += (
            '\n**The texture repeats**: every textured surface is one motif repeated on a square '
            f'lattice of {cfg.texture_period * 100:g} cm (+-25 % per material), like tiles or bricks.'
        )
    if cfg.shake_m or cfg.shake_deg:
        note += (
            f'\n**The hand shakes**: every pose moves by 1-4 Hz sinusoids of {cfg.shake_m * 1000:g} mm and '
            f'{cfg.shake_deg:g} deg (std per camera axis) about the path; images, depth and poses all '
            'follow it.'
        )
    return note


def source_markdown(cfg: SynthConfig, out_dir: Path) -> str:
    """SOURCE.md text: how to regenerate the folder and what its ground truth is."""
    command = shlex.join(['depth-fusion', 'synth', str(out_dir), *cfg.cli_args()])
    notes = _calibration_note(cfg) + _pose_note(cfg) + _sensor_note(cfg)
    config = yaml.safe_dump(cfg.as_dict(), sort_keys=False, default_flow_style=None).strip()
    return f"""# Synthetic room {sequence_name(cfg)}

Rendered by depth_fusion_ros (`depth_fusion_ros/data/synthetic/`): numpy ray casting of a
procedural room (floor, walls, ceiling, boxes, tables) with textured and texture-less
Lambertian materials, camera motion {_motion(cfg)}, seed {cfg.seed}.{notes}
No external data: free to use and redistribute.

Regenerate (bit-identical with the same package version):

    {command}

Ground truth: `depth/*.png` is the exact z-depth at pixel centres quantised to 1/5000 m
(0 = invalid, none here); `groundtruth.txt` holds the camera-to-world poses (exact unless
said above) at the same stamps as the images (no association error). `camera.yaml` has zero
plumb_bob distortion (the images are undistorted unless said above); colour has Gaussian sensor
noise of {cfg.noise_sigma:g} grey levels.

Config:

```yaml
{config}
```
"""


def write_synthetic_sequence(
    out_dir: str | Path, cfg: SynthConfig, *, overwrite: bool = False, show_progress: bool = False
) -> Path:
    """Render and write a TUM-layout folder (frames streamed to disk, not held in memory)."""
    out_dir = Path(out_dir)
    check_replaceable(out_dir, overwrite)  # say so before spending time on rendering
    scene, trajectory = build_world(cfg)
    frames = iter_frames(cfg, scene, trajectory, show_progress=show_progress)
    # The writer zips the rgb and depth iterables in lockstep, so tee buffers one frame.
    for_rgb, for_depth = itertools.tee((f.rgb, f.depth) for _, f, _ in frames)
    stamps = np.array([cfg.stamp(i) for i in range(cfg.frames)])
    pose_stamps, poses = pose_source(cfg, trajectory.poses)  # groundtruth.txt: the pose source's record
    return write_tum_folder(
        out_dir,
        cfg.pipeline_camera(),
        stamps,
        (rgb for rgb, _ in for_rgb),
        (depth for _, depth in for_depth),
        poses,
        name=sequence_name(cfg),
        source_md=source_markdown(cfg, out_dir),
        overwrite=overwrite,
        pose_stamps=None if np.array_equal(pose_stamps, stamps) else pose_stamps,
    )
