"""What the calibration check commands share (``check-focal``, ``check-sync``, ``check-mount``): the
options of a recording, reading it as the checks do, and a verdict as a printed line and an exit status."""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

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
    topics.add_argument(
        '--camera-from-pose-frame',
        nargs=7,
        type=float,
        metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
        default=None,
        help="the camera optical frame in the poses' frame (a body or IMU), as multi_view_node's "
        'parameter: the camera pose is the pose times this (also for a TUM folder)',
    )


#: The topic options and ``load_bag_sequence``'s keywords they set.
_TOPIC_OPTIONS = {
    'image_topic': 'rgb_topic',
    'camera_info_topic': 'camera_info_topic',
    'pose_topic': 'pose_topic',
}


def load_recording(args: argparse.Namespace):
    """The recording of ``args.source`` (TUM folder or rosbag2) at the working size, as the checks
    read it, its poses those of the camera (``--camera-from-pose-frame``)."""
    from pathlib import Path

    from ..data.tum import read_camera_yaml

    source = Path(args.source)
    if not source.exists():
        raise FileNotFoundError(f'{source} does not exist')
    calibration = read_camera_yaml(args.rgb_camera) if args.rgb_camera else None
    given = {opt: getattr(args, opt) for opt in _TOPIC_OPTIONS if getattr(args, opt, None)}
    if (source / 'metadata.yaml').is_file():
        from ..data.rosbag_read import load_bag_sequence

        sequence = load_bag_sequence(
            source,
            args.width,
            args.height,
            args.frames,
            depth_topic=None,
            calibration=calibration,
            **{_TOPIC_OPTIONS[opt]: topic for opt, topic in given.items()},
        )
    else:
        if given:
            named = ', '.join('--' + opt.replace('_', '-') for opt in given)
            raise ValueError(f'{named}: topics are for a rosbag2, and {source} is a TUM folder')
        from ..data.tum import load_tum_sequence

        sequence = load_tum_sequence(
            source, args.width, args.height, args.frames, require_depth=False, rgb_calibration=calibration
        )
    return camera_poses(sequence, getattr(args, 'camera_from_pose_frame', None))


def camera_poses(sequence: Any, camera_from_pose_frame: list[float] | None) -> Any:
    """``sequence`` with its poses (and its pose record) taken from the poses' frame to the camera
    optical frame, ``T_world_cam = T_world_pose @ T_pose_cam``, as multi_view_node does; as it
    is without one."""
    if camera_from_pose_frame is None:
        return sequence
    from ..nodes.robot_inputs import transform_from_parameter

    T_pose_cam = transform_from_parameter(list(camera_from_pose_frame), '--camera-from-pose-frame')
    stream = sequence.pose_stream
    moved = None if stream is None else (stream[0], np.asarray(stream[1]) @ T_pose_cam)
    return sequence.with_poses(sequence.poses @ T_pose_cam, pose_stream=moved)


def verdict_status(command: str, source: str, estimate: Any, pairs: int, config: Any, frames: int) -> int:
    """Print a check's verdict and return its exit status: 0 consistent, 3 disagrees, 4 cannot
    tell (not finished: said on stderr, with how far it got; or unobservable), 5 suspect (the
    focal check: off by its fit, not surely)."""
    if estimate is None:
        apart = f'{config.min_baseline:g} m or {config.min_rotation_deg:g} deg apart'
        print(
            f'depth-fusion {command}: {source}: not enough motion to tell: {pairs} of '
            f'{config.pairs} image pairs ({apart}) in {frames} frames',
            file=sys.stderr,
        )
        return 4
    print(f'{source}: {estimate.message()}')
    return {'consistent': 0, 'disagrees': 3, 'suspect': 5}.get(estimate.verdict, 4)


def run_paired_check(args: Any, command: str, config_type: type, check_frames: Any) -> int:
    """``check-focal`` and ``check-mount``: the recording loaded, the check (``config_type``
    with ``--pairs``) fed with its frames, the verdict printed; the exit status."""
    sequence = load_recording(args)
    config = config_type() if args.pairs is None else config_type(pairs=args.pairs)
    check = check_frames(sequence.camera, sequence.frames, config)
    return verdict_status(command, args.source, check.result, len(check.pairs), config, len(sequence))
