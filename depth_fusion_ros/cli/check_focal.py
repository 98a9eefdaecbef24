"""``depth-fusion check-focal``: is a recording's focal length the one its images and poses agree on?"""

from __future__ import annotations

import argparse

from .argtypes import subcommand
from .recordings import recording_arguments, run_paired_check

DESCRIPTION = """\
Check the focal length of a recording (a TUM-layout folder or a rosbag2 with images, camera
info and poses) against its own images and poses, before running the graph on it: the check
multi_view_node runs at start (focal_check.*; docs/multi_view.md, "The focal length check").
No ground-truth depth is needed. Prints the verdict with the focal length the images and poses
fit best. Exit status: 0 consistent, 3 disagrees, 4 cannot tell (too little motion or poses
too noisy: the check did not finish, or its standard error is too large), 5 suspect (the fit
is more than focal_check.threshold off, but not surely), 6 the images fit a lens distortion
that camera_info does not hold better than a focal change (whatever the focal verdict); 1 and
2 are errors.

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


def run(args: argparse.Namespace) -> int:
    from ..multiview.focal_check import FocalCheckConfig, check_frames

    return run_paired_check(args, 'check-focal', FocalCheckConfig, check_frames)
