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
