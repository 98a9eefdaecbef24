"""``depth-fusion check-sync``: are a recording's images and poses stamped by the same clock?"""

from __future__ import annotations

import argparse

from .argtypes import subcommand
from .recordings import load_recording, recording_arguments, verdict_status

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
    recording_arguments(p, 'time_offset_check')
    p.add_argument(
        '--pose-time-offset',
        type=float,
        default=0.0,
        help='seconds: read each pose at its image stamp plus this, as the node parameter does (0)',
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..evaluation.time_offset import shifted_sequence
    from ..multiview.time_offset_check import TimeOffsetCheckConfig, check_stream

    sequence = load_recording(args)
    if args.pose_time_offset:
        sequence = shifted_sequence(sequence, args.pose_time_offset)
    config = TimeOffsetCheckConfig() if args.pairs is None else TimeOffsetCheckConfig(pairs=args.pairs)
    check = check_stream(sequence.camera, sequence.frames, config, told=args.pose_time_offset)
    return verdict_status('check-sync', args.source, check.result, check.pairs, config, len(sequence))
