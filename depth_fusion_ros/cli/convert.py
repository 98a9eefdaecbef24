"""``depth-fusion convert SRC OUT_BAG``: a TUM folder, a ROS 1 bag or a robot's rosbag2 -> a rosbag2
in the layout the nodes, ``run`` and ``evaluate`` read."""

from __future__ import annotations

import argparse

from .argtypes import at_least

DESCRIPTION = """\
Convert a posed RGB-D recording into a ROS 2 bag (rosbag2) that `depth-fusion run` and the
nodes can play.

SRC is one of
  * a TUM RGB-D folder: rgb.txt, depth.txt, groundtruth.txt, camera.yaml (ROS camera-info
    YAML with K and the distortion) and the images they name;
  * a ROS 1 .bag file (e.g. a TUM RGB-D sequence as downloaded). Its camera_info often holds
    default intrinsics: pass --camera-yaml with the real calibration;
  * a rosbag2 folder a robot recorded (ros2 bag record): its own topics (--src-*-topic),
    colour raw or on <topic>/compressed, depth 16UC1 mm or 32FC1 m registered to the colour
    camera, poses on a topic or only on /tf (which the nodes cannot subscribe to: tf2_msgs is
    not on pip, so convert them here).
For both bags, poses come from --groundtruth (TUM 'timestamp tx ty tz qx qy qz qw',
camera-to-world), else from a pose topic (--src-pose-topic: PoseStamped,
PoseWithCovarianceStamped, Odometry or TransformStamped), else from the /tf and /tf_static
chain --tf-world-frame -> --tf-camera-frame.

OUT_BAG is the rosbag2 folder to create (mcap by default). Header stamp = bag time throughout;
written per colour frame, with the colour stamp:
  <rgb-topic>          sensor_msgs/Image rgb8, the original (distorted) colour image
                       (with --compressed: sensor_msgs/CompressedImage on <rgb-topic>/compressed)
  <camera-info-topic>  sensor_msgs/CameraInfo, K and D of the colour camera
  <depth-topic>        sensor_msgs/Image 32FC1, ground-truth depth in metres (NaN = none)
and the poses, as the pose source published them:
  <pose-topic>         geometry_msgs/PoseStamped, camera-to-world, frame <world-frame>: the
                       source's own samples at their own stamps (groundtruth.txt's rows, a
                       pose topic's messages) from 0.5 s before the first frame written to
                       0.5 s after the last; from a /tf chain, one pose per colour frame
                       interpolated at its stamp
Colour frames without a pose (interpolated at their stamp) or without depth within
--depth-max-gap are skipped and counted. The bag appears only when the conversion completes.
"""

EPILOG = """\
examples:
  depth-fusion convert data/rgbd_dataset_freiburg1_xyz fr1_xyz.mcap --frames 100
  depth-fusion convert data/rgbd_dataset_freiburg1_xyz fr1_xyz_jpeg --compressed jpeg
  depth-fusion convert --repair runs/crashed.partial/crashed runs/crashed_repaired
  depth-fusion convert fr1_xyz.bag fr1_xyz_ros2 --groundtruth fr1_xyz-groundtruth.txt \\
      --camera-yaml camera.yaml
  depth-fusion convert robot_recording robot_ros2 --src-rgb-topic /camera/color/image_raw \\
      --src-camera-info-topic /camera/color/camera_info \\
      --src-depth-topic /camera/aligned_depth_to_color/image_raw --tf-world-frame odom
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'convert',
        help="TUM folder, ROS 1 bag or a robot's rosbag2 -> rosbag2 (mcap or sqlite3)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument('src', metavar='SRC', help='TUM folder, ROS 1 .bag file or rosbag2 folder')
    p.add_argument('out', metavar='OUT_BAG', help='rosbag2 folder to create')
    p.add_argument(
        '--storage', choices=('mcap', 'sqlite3'), default='mcap', help='bag storage (default: %(default)s)'
    )
    p.add_argument(
        '--frames',
        type=at_least(1, '--frames'),
        default=None,
        metavar='N',
        help='write only the first N usable frames',
    )
    p.add_argument(
        '--overwrite',
        action='store_true',
        help='replace OUT_BAG if it is a rosbag2 depth-fusion wrote (never a recording)',
    )
    p.add_argument(
        '--repair',
        action='store_true',
        help='SRC is a rosbag2 that a crashed recorder left truncated: copy its readable messages '
        'into a clean OUT_BAG',
    )
    p.add_argument('--no-depth', action='store_true', help='do not write ground-truth depth')
    p.add_argument(
        '--depth-max-gap',
        type=float,
        default=0.02,
        metavar='SEC',
        help='largest colour-depth stamp difference to associate (default: %(default)s s)',
    )
    p.add_argument(
        '--compressed',
        nargs='?',
        const='png',
        choices=('png', 'jpeg'),
        default=None,
        metavar='png|jpeg',
        help='write colour as sensor_msgs/CompressedImage on <rgb-topic>/compressed (image_transport '
        "'compressed'); png (default: lossless, the evaluation matches the raw bag) or jpeg (what "
        'robots record: much smaller, lossy)',
    )
    p.add_argument(
        '--jpeg-quality',
        type=int,
        default=None,
        metavar='Q',
        help='JPEG quality 1-100 with --compressed jpeg (default: 90)',
    )
    p.add_argument('--no-progress', action='store_true', help='no progress bar')
    out = p.add_argument_group('output topics and frames')
    out.add_argument('--rgb-topic', default='/camera/rgb/image_color', help='(default: %(default)s)')
    out.add_argument('--camera-info-topic', default='/camera/rgb/camera_info', help='(default: %(default)s)')
    out.add_argument('--depth-topic', default='/camera/depth/image', help='(default: %(default)s)')
    out.add_argument('--pose-topic', default='/camera/pose', help='(default: %(default)s)')
    out.add_argument(
        '--camera-frame', default='camera_rgb_optical_frame', help='camera frame_id (default: %(default)s)'
    )
    out.add_argument('--world-frame', default='world', help='frame_id of the poses (default: %(default)s)')
    recorded = p.add_argument_group('recorded bag sources only (ROS 1 .bag or rosbag2)')
    recorded.add_argument(
        '--groundtruth', metavar='FILE', help='poses from a TUM groundtruth.txt (preferred for TUM bags)'
    )
    recorded.add_argument(
        '--camera-yaml', metavar='FILE', help='intrinsics and distortion from a ROS camera-info YAML'
    )
    recorded.add_argument('--src-rgb-topic', default='/camera/rgb/image_color', help='(default: %(default)s)')
    recorded.add_argument(
        '--src-camera-info-topic', default='/camera/rgb/camera_info', help='(default: %(default)s)'
    )
    recorded.add_argument('--src-depth-topic', default='/camera/depth/image', help='(default: %(default)s)')
    recorded.add_argument(
        '--src-pose-topic',
        default='/camera/pose',
        help='pose topic (PoseStamped, PoseWithCovarianceStamped, Odometry or TransformStamped),'
        ' if the bag has one',
    )
    recorded.add_argument(
        '--tf-world-frame', default=None, help='/tf poses: the world frame (default: world)'
    )
    recorded.add_argument(
        '--tf-camera-frame', default=None, help="/tf poses: the camera frame (default: the images' frame_id)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..data.rosbag_convert import BagTopics, FrameIds, convert
    from .paths import check_output

    if args.frames is not None and args.frames <= 0:
        raise ValueError(f'--frames must be positive, got {args.frames}')
    from ..data.compressed import DEFAULT_JPEG_QUALITY, ColourFormat

    if args.jpeg_quality is not None and args.compressed != 'jpeg':
        raise ValueError('--jpeg-quality only applies with --compressed jpeg')
    quality = DEFAULT_JPEG_QUALITY if args.jpeg_quality is None else args.jpeg_quality
    if not 1 <= quality <= 100:
        raise ValueError(f'--jpeg-quality must be in [1, 100], got {quality}')
    check_output(args.out, 'OUT_BAG', exists_ok=args.overwrite, overwrite_flag='--overwrite', bag=True)
    if args.repair:
        from ..data.bag_recovery import repair_bag

        written, summary = repair_bag(args.src, args.out, storage=args.storage, overwrite=args.overwrite)
        print(f'{summary}; wrote {written} messages to {args.out} ({args.storage})')
        return 0
    options = {
        'colour': ColourFormat(args.compressed, quality),
        'storage': args.storage,
        'max_frames': args.frames,
        'topics': BagTopics(args.rgb_topic, args.camera_info_topic, args.depth_topic, args.pose_topic),
        'frame_ids': FrameIds(args.camera_frame, args.world_frame),
        'depth_max_gap': args.depth_max_gap,
        'include_depth': not args.no_depth,
        'overwrite': args.overwrite,
        'show_progress': not args.no_progress,
        'groundtruth': args.groundtruth,
        'camera_yaml': args.camera_yaml,
        'tf_world_frame': args.tf_world_frame,
        'tf_camera_frame': args.tf_camera_frame,
    }
    src = Path(args.src)
    if not (src / 'rgb.txt').is_file():  # a recorded bag, not a TUM folder
        options['source_topics'] = BagTopics(
            args.src_rgb_topic, args.src_camera_info_topic, args.src_depth_topic, args.src_pose_topic
        )
    result = convert(src, args.out, **options)
    counts = ', '.join(f'{topic} {n}' for topic, n in result.messages.items())
    colour = f', colour {args.compressed}-compressed' if args.compressed else ''
    print(f'wrote {result.path} ({args.storage}{colour}): {result.frames} frames in {result.seconds:.1f} s')
    print(f'  poses from {result.pose_source}; messages: {counts}')
    if result.dropped:
        print(f'  skipped colour frames: {result.dropped}')
    return 0
