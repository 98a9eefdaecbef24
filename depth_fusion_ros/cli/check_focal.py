"""``depth-fusion check-focal``: is a recording's focal length the one its images and poses agree on?"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .argtypes import at_least, subcommand

DESCRIPTION = """\
Check the focal length of a recording (a TUM-layout folder or a rosbag2 with images, camera
info and poses) against its own images and poses, before running the graph on it: the check
multi_view_node runs at start (focal_check.*; docs/multi_view.md, "The focal length check").
No ground-truth depth is needed. Prints the verdict with the focal length the images and poses
fit best. Exit status: 0 consistent, 3 disagrees, 4 cannot tell (too little motion or poses
too noisy: the check did not finish, or its standard error is too large); 1 and 2 are errors.

examples:
  depth-fusion check-focal ~/data/rgbd_dataset_freiburg1_desk
  depth-fusion check-focal runs/lab_bag --pairs 20
  depth-fusion check-focal 7scenes_redkitchen --rgb-camera config/cameras/7scenes_rgb.yaml
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = subcommand(
        sub, 'check-focal', "check a recording's focal length against its images and poses", DESCRIPTION
    )
    recording_arguments(p, 'focal_check')
    p.set_defaults(func=run)


def recording_arguments(p: argparse.ArgumentParser, stage: str) -> None:
    """The options a calibration check of a recording takes (``check-focal``, ``check-sync``)."""
    p.add_argument('source', help='TUM-layout folder or rosbag2 folder')
    p.add_argument(
        '--rgb-camera',
        metavar='YAML',
        help="the colour camera's calibration, if camera.yaml is another one's",
    )
    p.add_argument('--frames', type=at_least(2, '--frames'), default=600, help='frames read at most (600)')
    p.add_argument(
        '--pairs',
        type=at_least(5, '--pairs'),
        default=None,
        help=f'image pairs the estimate uses ({stage}.pairs)',
    )
    p.add_argument(
        '--width', type=at_least(16, '--width'), default=320, help='working width (320, as the node)'
    )
    p.add_argument('--height', type=at_least(16, '--height'), default=240, help='working height (240)')


def load_recording(args: argparse.Namespace):
    """The recording of ``args.source`` (TUM folder or rosbag2) at the working size, as the checks read it."""
    from pathlib import Path

    source = Path(args.source)
    if not source.exists():
        raise FileNotFoundError(f'{source} does not exist')
    if (source / 'metadata.yaml').is_file():
        from ..data.rosbag_read import load_bag_sequence
        from ..data.tum import read_camera_yaml

        calibration = read_camera_yaml(args.rgb_camera) if args.rgb_camera else None
        return load_bag_sequence(
            source, args.width, args.height, args.frames, depth_topic=None, calibration=calibration
        )
    from ..data.tum import load_tum_sequence, read_camera_yaml

    calibration = read_camera_yaml(args.rgb_camera) if args.rgb_camera else None
    return load_tum_sequence(
        source, args.width, args.height, args.frames, require_depth=False, rgb_calibration=calibration
    )


def run(args: argparse.Namespace) -> int:
    from ..multiview.focal_check import FocalCheckConfig, check_frames

    sequence = load_recording(args)
    config = FocalCheckConfig() if args.pairs is None else FocalCheckConfig(pairs=args.pairs)
    check = check_frames(sequence.camera, sequence.frames, config)
    return verdict_status('check-focal', args.source, check.result, len(check.pairs), config, len(sequence))


def verdict_status(command: str, source: str, estimate: Any, pairs: int, config: Any, frames: int) -> int:
    """Print a check's verdict and return its exit status: 0 consistent, 3 disagrees, 4 cannot
    tell (not finished: said on stderr, with how far it got; or unobservable)."""
    if estimate is None:
        apart = f'{config.min_baseline:g} m or {config.min_rotation_deg:g} deg apart'
        print(
            f'depth-fusion {command}: {source}: not enough motion to tell: {pairs} of '
            f'{config.pairs} image pairs ({apart}) in {frames} frames',
            file=sys.stderr,
        )
        return 4
    print(f'{source}: {estimate.message()}')
    return {'consistent': 0, 'disagrees': 3}.get(estimate.verdict, 4)
