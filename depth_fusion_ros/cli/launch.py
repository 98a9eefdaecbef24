"""``depth-fusion launch``: the node graph for a live camera and a SLAM pose publisher."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import at_least

DESCRIPTION = """\
Start multi_view_node, single_view_node and fusion_node (and map_node with --map) as their own
processes, for a live camera: what `ros2 launch depth_fusion_ros depth_fusion.launch.py` does
with a ROS install, in one command where pip has no `ros2 launch`. Every node gets the same
--params file and --set values; the multi-view node reads its inputs from --image,
--camera-info, --pose and --corrected-path. The nodes join this shell's ROS domain
(ROS_DOMAIN_ID) and each logs to this terminal, or to DIR/NODE.log with --log-dir.

The nodes are forked from a process that imported torch once, so the graph is ready sooner
than three console scripts started at once (DEPTH_FUSION_FORK_NODES=0 starts the scripts).
Ctrl-C or SIGTERM stops them all and exits 0 when every node stopped cleanly and a keyframe
was fused; 1, with the reason, when nothing was. A node that ends on its own (a bad parameter,
a crash, a kill) stops the others, and the exit code is 1.

examples:
  depth-fusion launch --pose /orb_slam3/camera_pose
  depth-fusion launch --params my.yaml --image /cam/image_raw --camera-info /cam/camera_info \\
      --pose /slam/pose --map --log-dir logs/
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'launch',
        help='start the node graph for a live camera (the launch file without a ROS install)',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument('--params', type=Path, metavar='FILE', help='ROS params file for every node')
    p.add_argument('--image', metavar='TOPIC', help='colour image topic (default /camera/rgb/image_color)')
    p.add_argument('--camera-info', metavar='TOPIC', help='its camera_info (default /camera/rgb/camera_info)')
    p.add_argument('--pose', metavar='TOPIC', help='camera-to-world pose from SLAM (default /camera/pose)')
    p.add_argument(
        '--corrected-path',
        metavar='TOPIC',
        help="nav_msgs/Path: the SLAM's corrected trajectory after a loop closure (default "
        '/camera/corrected_path)',
    )
    p.add_argument('--map', action='store_true', help='also start map_node (a TSDF map, docs/mapping.md)')
    p.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='NODE.PARAM=VALUE',
        help='override one node parameter, e.g. --set fusion_node.fusion.align_scale=true (repeatable)',
    )
    p.add_argument('--log-dir', type=Path, metavar='DIR', help="write each node's log to DIR/NODE.log")
    p.add_argument(
        '--threads',
        type=at_least(1, '--threads'),
        metavar='N',
        help='torch CPU threads per node (default: cores / 3; OMP_NUM_THREADS wins)',
    )
    p.set_defaults(func=run)


def options_from_args(args: argparse.Namespace):  # -> LaunchOptions (import kept lazy)
    from ..nodes.graph.live import LaunchOptions
    from .overrides import check_node_overrides, check_params_file, parse_overrides
    from .paths import check_output
    from .topic_names import check_topic_name

    if args.params is not None and not args.params.is_file():
        raise FileNotFoundError(f'--params {args.params}: no such file')
    overrides = parse_overrides(args.set, 'NODE')
    check_node_overrides(overrides)
    check_params_file(args.params)
    for node in overrides:
        if node == 'bag_replayer' or (node == 'map_node' and not args.map):
            hint = '; add --map' if node == 'map_node' else ' (launch plays no bag)'
            raise ValueError(f'--set {node}.*: {node} is not started{hint}')
    if args.log_dir is not None:
        check_output(args.log_dir, '--log-dir')
    inputs = {
        key: check_topic_name(f'--{key.replace("_", "-")}', topic)
        for key, topic in (
            ('image', args.image),
            ('camera_info', args.camera_info),
            ('pose', args.pose),
            ('corrected_path', args.corrected_path),
        )
        if topic is not None
    }
    return LaunchOptions(
        params_file=args.params,
        with_map=args.map,
        inputs=inputs,
        overrides=overrides,
        log_dir=args.log_dir,
        threads_per_node=args.threads,
    )


def run(args: argparse.Namespace) -> int:
    from ..nodes.graph.live import launch

    return launch(options_from_args(args))
