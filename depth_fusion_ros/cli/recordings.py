"""What the calibration check commands share (``check-focal``, ``check-sync``, ``check-mount``): the
options of a recording, reading it as the checks do, and a verdict as a printed line and an exit status."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .argtypes import at_least


def recording_arguments(p: argparse.ArgumentParser, stage: str) -> None:
    """The options a calibration check of a recording takes (``check-focal``, ``-sync``, ``-mount``)."""
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
    topic_arguments(p, depth=False)


def topic_arguments(p: argparse.ArgumentParser, depth: bool) -> None:
    """The options of a robot's rosbag2 (its topics; ``depth``: a ground-truth depth topic too)
    and of poses that are a body's, not the camera's (``data.recording.load_recording``)."""
    topics = p.add_argument_group("a robot's rosbag2 (ros2 bag record): its topics and frames")
    topics.add_argument(
        '--image-topic',
        default=None,
        help='colour images, raw or <topic>/compressed (/camera/rgb/image_color)',
    )
    topics.add_argument('--camera-info-topic', default=None, help='camera_info (/camera/rgb/camera_info)')
    topics.add_argument(
        '--pose-topic',
        default=None,
        help='poses: PoseStamped, PoseWithCovarianceStamped, Odometry or TransformStamped (/camera/pose)',
    )
    if depth:
        topics.add_argument(
            '--depth-topic',
            default=None,
            help='ground-truth depth registered to the colour camera, 32FC1 m or 16UC1 mm, e.g. '
            '/camera/aligned_depth_to_color/image_raw (/camera/depth/image)',
        )
    topics.add_argument(
        '--camera-from-pose-frame',
        nargs=7,
        type=float,
        metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
        default=None,
        help="the camera optical frame in the poses' frame (a body or IMU), as multi_view_node's "
        'parameter: the camera pose is the pose times this (also for a TUM folder)',
    )


def given_topics(args: argparse.Namespace) -> dict[str, str]:
    """The topic options given on the command line (``data.recording.TOPIC_KEYWORDS`` names)."""
    from ..data.recording import TOPIC_KEYWORDS

    return {name: getattr(args, name) for name in TOPIC_KEYWORDS if getattr(args, name, None)}


def load_recording(args: argparse.Namespace):
    """The recording of ``args.source`` (TUM folder or rosbag2) at the working size, as the checks
    read it (no depth), its poses those of the camera (``--camera-from-pose-frame``)."""
    from ..data import recording
    from ..data.tum import read_camera_yaml

    return recording.load_recording(
        args.source,
        args.width,
        args.height,
        args.frames,
        calibration=read_camera_yaml(args.rgb_camera) if args.rgb_camera else None,
        topics=given_topics(args),
        camera_from_pose_frame=args.camera_from_pose_frame,
        with_depth=False,
    )


def verdict_status(command: str, source: str, estimate: Any, pairs: int, config: Any, frames: int) -> int:
    """Print a check's verdict and return its exit status: 0 consistent, 3 disagrees (the
    mount check: a turn, or the poses inverted), 4 cannot tell (not finished: said on stderr,
    with how far it got; or unobservable), 5 suspect (the focal check: off by its fit, not
    surely), 6 a lens distortion camera_info does not hold (the focal check's pairs fit one
    better than a focal change, whatever its verdict)."""
    if estimate is None:
        apart = f'{config.min_baseline:g} m or {config.min_rotation_deg:g} deg apart'
        print(
            f'depth-fusion {command}: {source}: not enough motion to tell: {pairs} of '
            f'{config.pairs} image pairs ({apart}) in {frames} frames',
            file=sys.stderr,
        )
        return 4
    print(f'{source}: {estimate.message()}')
    if getattr(estimate, 'lens_distorted', False):
        return 6
    return {'consistent': 0, 'disagrees': 3, 'inverted': 3, 'suspect': 5}.get(estimate.verdict, 4)


def run_paired_check(args: Any, command: str, config_type: type, check_frames: Any) -> int:
    """``check-focal`` and ``check-mount``: the recording loaded, the check (``config_type``
    with ``--pairs``) fed with its frames, the verdict printed; the exit status."""
    sequence = load_recording(args)
    config = config_type() if args.pairs is None else config_type(pairs=args.pairs)
    check = check_frames(sequence.camera, sequence.frames, config)
    return verdict_status(command, args.source, check.result, len(check.pairs), config, len(sequence))
