"""``depth-fusion synth OUT_DIR``: render a synthetic posed RGB-D sequence as a TUM folder."""

from __future__ import annotations

import argparse
import dataclasses
import time

from .argtypes import at_least

DESCRIPTION = """\
Render a seeded synthetic indoor room (floor, walls, ceiling, boxes, tables; textured and
texture-less surfaces) along a camera trajectory, with exact depth and poses, and write it in
the TUM RGB-D layout: rgb/ and depth/ PNGs (depth x5000, 0 = invalid), rgb.txt, depth.txt,
groundtruth.txt (camera-to-world), camera.yaml (ROS camera info) and SOURCE.md.

The same options (seed included) give bit-identical output. One seed gives the same room
for --parallax high and low, so the two regimes can be compared on one scene.
"""

EPILOG = """\
examples:
  depth-fusion synth artifacts/room                       # 100 frames 640x480, high parallax
  depth-fusion synth artifacts/room_low --parallax low --seed 3
  depth-fusion synth artifacts/small --frames 24 --width 320 --height 240
  depth-fusion synth artifacts/rot --stress rotation --frames 60   # a stress case (see --stress)
"""


#: Help of the scalar options (``{default}``: the field's default), by ``SynthConfig`` field.
SCALAR_HELP: dict[str, str] = {
    'noise_sigma': 'sensor noise std, grey levels (default {default})',
    'textureless_fraction': 'fraction of surfaces with a flat colour (default {default})',
    'room_jitter': 'per-seed relative jitter of the room size (default {default})',
    'step_translation': 'stress motions: metres between consecutive frames (default {default})',
    'step_rotation_deg': 'stress motions: degrees between consecutive frames (default {default})',
    'texture_contrast': 'contrast of the textures in (0, 1] (default {default}; low = faint texture)',
    'focal_error': (
        'relative error of the focal lengths written to camera.yaml (rendering uses the true ones; '
        'default {default})'
    ),
    'pose_noise_m': (
        'std of a per-frame jitter (m) of the poses written to groundtruth.txt (rendering uses '
        'the true ones; default {default})'
    ),
    'pose_noise_deg': 'the same jitter of the rotations, degrees (default {default})',
    'pose_scale': (
        'positions (groundtruth.txt) and depth images in a unit of 1/this metres, as a monocular SLAM '
        'gives them; images rendered in metres (0.05..1; default {default})'
    ),
    'mount_tilt_deg': (
        'degrees: the poses written to groundtruth.txt are the true ones turned about the camera x '
        'axis, a camera mounted tilted against its pose frame (-10..10; default {default})'
    ),
    'pose_time_offset': (
        'seconds: the poses written to groundtruth.txt are the true ones this much later, a camera / '
        'pose-source time offset (at most one frame period; default {default})'
    ),
    'exposure_time': (
        'seconds the shutter is open around each stamp: a moving camera blurs the image along its '
        'motion (at most one frame period; default {default}: sharp)'
    ),
    'readout_time': (
        'seconds a rolling shutter takes to read the rows out, top to bottom, around each stamp: '
        'a moving camera skews the image (at most one frame period; default {default}: global)'
    ),
    'blur_samples': 'renders over --exposure-time and --readout-time (default {default})',
    'gain_sigma': "std of each frame's log gain, an auto-exposure that changes from frame to frame "
    '(default {default}: constant exposure)',
    'walkers': 'person-sized boxes walking back and forth across the view: a world that is not static '
    '(0-4; default {default})',
    'walker_speed': 'their walking speed in m/s (default {default})',
    'texture_period': (
        'repetitive texture: every textured surface repeats one motif about this often, in m '
        '(0.02-0.5: tiles, bricks, shelves; default {default}: aperiodic patterns)'
    ),
    'shake_m': (
        "a hand's shake: every pose moves by 1-4 Hz sinusoids of this std per camera axis, in m "
        '(0-0.05; default {default}: the smooth path)'
    ),
    'shake_deg': 'the same shake of the rotations, degrees (0-5; default {default})',
    'lens_k1': (
        'radial distortion k1 of the lens the images are rendered through (plumb_bob; camera.yaml '
        'says none; -0.4..0.4, default {default})'
    ),
}


def register(sub: argparse._SubParsersAction) -> None:
    from ..data.synthetic import MOTIONS, PARALLAX_MODES, POSE_FRAMES, STRESS_CASES, SynthConfig

    d = SynthConfig()
    p = sub.add_parser(
        'synth',
        help='render a synthetic posed RGB-D sequence (TUM layout) with exact depth and poses',
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument('out_dir', metavar='OUT_DIR', help='folder to create (must not exist unless --overwrite)')
    p.add_argument(
        '--frames',
        type=at_least(1, '--frames'),
        default=d.frames,
        help=f'number of frames (default {d.frames})',
    )
    p.add_argument('--width', type=int, default=d.width, help=f'image width in pixels (default {d.width})')
    p.add_argument(
        '--height', type=int, default=d.height, help=f'image height in pixels (default {d.height})'
    )
    p.add_argument('--fps', type=float, default=d.fps, help=f'frame rate for the stamps (default {d.fps:g})')
    p.add_argument(
        '--parallax',
        choices=PARALLAX_MODES,
        default=d.parallax,
        help="'high': 0.6-1.2 m lateral sweep; 'low': panning with a few cm of translation (default high)",
    )
    p.add_argument(
        '--seed', type=int, default=d.seed, help=f'random seed of room, trajectory, noise (default {d.seed})'
    )
    p.add_argument(
        '--fx', type=float, default=None, help='focal length x in pixels (default 525 * width / 640)'
    )
    p.add_argument(
        '--fy', type=float, default=None, help='focal length y in pixels (default 525 * height / 480)'
    )
    _scalar_options(p, ('noise_sigma', 'textureless_fraction'))
    p.add_argument(
        '--room-size',
        type=float,
        nargs=3,
        metavar=('W', 'D', 'H'),
        default=list(d.room_size),
        help='nominal room width, depth, height in metres (default %(default)s)',
    )
    _scalar_options(p, ('room_jitter',))
    p.add_argument('--boxes', type=int, default=d.boxes, help=f'number of boxes (default {d.boxes})')
    p.add_argument('--tables', type=int, default=d.tables, help=f'number of tables (default {d.tables})')
    p.add_argument(
        '--sweep',
        type=float,
        default=None,
        help='lateral sweep of --parallax high in m (default random 0.6-1.2)',
    )
    p.add_argument(
        '--no-antialias', dest='antialias', action='store_false', help='do not supersample silhouette pixels'
    )
    p.add_argument('--t0', type=float, default=d.t0, help=f'stamp of the first frame in s (default {d.t0:g})')
    p.add_argument(
        '--pose-frame',
        choices=POSE_FRAMES,
        default=d.pose_frame,
        help="whose poses groundtruth.txt holds: 'optical', the camera's, 'body', a REP 103 body "
        "frame's (x forward, z up) holding it, as odometry published without camera_from_pose_frame "
        "gives them, or 'inverted', the camera's inverted (T_cw, as a SLAM system keeps them) "
        f'(default {d.pose_frame})',
    )
    p.add_argument(
        '--motion',
        choices=MOTIONS,
        default=d.motion,
        help="'parallax': the --parallax trajectory; 'rotation_sweep', 'keyframe_stream', 'forward': "
        'stress motions with fixed per-frame steps (default parallax)',
    )
    _scalar_options(
        p,
        (
            'step_translation',
            'step_rotation_deg',
            'texture_contrast',
            'focal_error',
            'pose_noise_m',
            'pose_noise_deg',
            'mount_tilt_deg',
            'pose_scale',
            'pose_time_offset',
            'exposure_time',
            'readout_time',
            'blur_samples',
            'gain_sigma',
            'walkers',
            'walker_speed',
            'texture_period',
            'shake_m',
            'shake_deg',
            'lens_k1',
        ),
    )
    p.add_argument(
        '--stress',
        choices=tuple(STRESS_CASES),
        default=None,
        help='start from a named stress case (data/synthetic/stress.py); options given explicitly win',
    )
    p.add_argument(
        '--overwrite', action='store_true', help='replace OUT_DIR if depth-fusion wrote it (or it is empty)'
    )
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    # Every field's option defaults to None (its help names the field's default): an option
    # given is used as given, also when it equals the default (``--stress time_offset
    # --pose-time-offset 0`` is in sync); one left out takes the preset's value, else the default.
    p.set_defaults(func=run, **{f.name: None for f in dataclasses.fields(SynthConfig)})


def _scalar_options(p: argparse.ArgumentParser, names: tuple[str, ...]) -> None:
    """One option per scalar ``SynthConfig`` field, named, typed and defaulted from the field
    (``--pose-noise-m`` for ``pose_noise_m``, as ``SynthConfig.cli_args`` writes it back), with
    its help from :data:`SCALAR_HELP`."""
    from ..data.synthetic import SynthConfig

    d = SynthConfig()
    for name in names:
        value = getattr(d, name)
        text = SCALAR_HELP[name].format(default=f'{value:g}')
        p.add_argument('--' + name.replace('_', '-'), type=type(value), default=value, help=text)


def config_from_args(args: argparse.Namespace):
    """The ``SynthConfig`` of parsed arguments (raises ValueError naming a bad option)."""
    from ..data.synthetic import STRESS_CASES, SynthConfig

    preset = STRESS_CASES.get(getattr(args, 'stress', None) or '', {})
    defaults = SynthConfig()

    def pick(name: str, value):
        # A stress preset fills the options left out; the rest take the field's default.
        if value is not None:
            return value
        return preset.get(name, getattr(defaults, name))

    # Every field has its option under the same name (``SynthConfig.cli_args`` writes them so).
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(SynthConfig)}
    if values['room_size'] is not None:
        values['room_size'] = tuple(values['room_size'])
    return SynthConfig(**{name: pick(name, value) for name, value in values.items()})


def run(args: argparse.Namespace) -> int:
    from ..data.synthetic import sequence_name, write_synthetic_sequence

    cfg = config_from_args(args)
    start = time.perf_counter()
    out = write_synthetic_sequence(args.out_dir, cfg, overwrite=args.overwrite, show_progress=not args.quiet)
    elapsed = time.perf_counter() - start
    print(
        f'wrote {cfg.frames} frames {cfg.width}x{cfg.height} ({sequence_name(cfg)}) '
        f'to {out} in {elapsed:.1f} s ({elapsed / cfg.frames:.3f} s/frame)'
    )
    return 0
