"""``depth-fusion check-sync``: are a recording's images and poses stamped by the same clock?"""

from __future__ import annotations

import argparse
import sys

from .argtypes import at_least, subcommand
from .check_focal import load_recording

DESCRIPTION = """\
Check a recording (a TUM-layout folder or a rosbag2 with images, camera info and poses) for a
time offset between its images and its poses, before running the graph on it: the check
multi_view_node runs at start (time_offset_check.*; docs/multi_view.md, "The time offset
check"). No ground-truth depth is needed. Prints the verdict with the pose_time_offset the
images fit best. Exit status: 0 in sync, 3 out of sync, 4 cannot tell (motion too smooth or
too little of it, or poses too noisy); 1 and 2 are errors.

examples:
  depth-fusion check-sync ~/data/rgbd_dataset_freiburg1_desk
  depth-fusion check-sync runs/lab_bag --pose-time-offset 0.015
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = subcommand(sub, 'check-sync', "check a recording's images and poses for a time offset", DESCRIPTION)
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
        help='image pairs the estimate uses (time_offset_check.pairs)',
    )
    p.add_argument(
        '--pose-time-offset',
        type=float,
        default=0.0,
        help='seconds: read each pose at its image stamp plus this, as the node parameter does (0)',
    )
    p.add_argument(
        '--width', type=at_least(16, '--width'), default=320, help='working width (320, as the node)'
    )
    p.add_argument('--height', type=at_least(16, '--height'), default=240, help='working height (240)')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..evaluation.time_offset import shifted_sequence
    from ..multiview.time_offset_check import TimeOffsetCheckConfig, check_stream

    sequence = load_recording(args)
    if args.pose_time_offset:
        sequence = shifted_sequence(sequence, args.pose_time_offset)
    config = TimeOffsetCheckConfig() if args.pairs is None else TimeOffsetCheckConfig(pairs=args.pairs)
    check = check_stream(sequence.camera, sequence.frames, config, told=args.pose_time_offset)
    estimate = check.result
    if estimate is None:
        apart = f'{config.min_baseline:g} m or {config.min_rotation_deg:g} deg apart'
        print(
            f'depth-fusion check-sync: {args.source}: not enough motion to tell: {check.pairs} of '
            f'{config.pairs} image pairs ({apart}) in {len(sequence.frames)} frames',
            file=sys.stderr,
        )
        return 4
    print(f'{args.source}: {estimate.message()}')
    return {'consistent': 0, 'disagrees': 3}.get(estimate.verdict, 4)
