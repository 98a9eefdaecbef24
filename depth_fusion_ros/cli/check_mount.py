"""``depth-fusion check-mount``: is a recording's camera mounted as its poses say?"""

from __future__ import annotations

import argparse

from .argtypes import subcommand
from .recordings import recording_arguments, run_paired_check

DESCRIPTION = """\
Check the optical frame of a recording (a TUM-layout folder or a rosbag2 with images, camera
info and poses) against its own images: the check whose verdict multi_view_node takes once the time
offset check has settled (mount_check.*; docs/multi_view.md, "The mount check"). A camera mounted a
degree or two more tilted than its told pose frame (camera_from_pose_frame, a hand-eye
calibration) turns every relative pose; the images fit the poses best turned back. No
ground-truth depth is needed; run check-sync first (clocks out of sync fake a turn). Prints the
verdict with the rotation the images fit, or that the poses fit them inverted (the world's pose
in the camera, T_cw, given for the camera's). Exit status: 0 consistent, 3 disagrees (a turn, or
the poses inverted), 4 cannot tell
(too little motion: the check needs 20 image pairs 10 cm apart, about 2 m of travel, or 8
when the turn is already sure by three standard errors, or no direction of the turn is pinned
down); 1 and 2 are errors.

examples:
  depth-fusion check-mount ~/data/rgbd_dataset_freiburg1_desk
  depth-fusion check-mount runs/robot_bag --pairs 30
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = subcommand(
        sub, 'check-mount', "check a recording's camera mount against its images and poses", DESCRIPTION
    )
    recording_arguments(p, 'mount_check')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..multiview.mount_check import MountCheckConfig, check_frames

    return run_paired_check(args, 'check-mount', MountCheckConfig, check_frames)
