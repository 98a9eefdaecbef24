"""``depth-fusion run``: the ROS 2 node graph on a rosbag2, composed or as separate processes."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import at_least

DESCRIPTION = """\
Play a rosbag2 (mcap or sqlite3) through bag_replayer -> multi_view_node + single_view_node ->
fusion_node, over real DDS, and optionally record the outputs. The run ends by itself: at the end
of the bag it waits until every announced keyframe has its fused output (or --flush-timeout),
closes the recording, stops the nodes and exits 0. Ctrl-C stops everything (exit 130) and leaves
the partial recording in OUT.partial/.

By default the nodes run composed in this process (each on its own executor thread);
--processes starts the console scripts (bag_replayer, single_view_node, multi_view_node,
fusion_node) as separate processes with the same params file. A Fast DDS profile with a 10 MB
shared-memory segment is applied (to this process and the children) so 640x480 images are not
lost between processes, the camera image topics read over UDP (docs/nodes.md, "Large raw
images"); set FASTRTPS_DEFAULT_PROFILES_FILE yourself to use another.

recorded topics (--record): /depth_fusion/fused/{depth,confidence,camera_info},
/depth_fusion/multi_view/depth, /depth_fusion/single_view/depth, /depth_fusion/keyframe/{image,pose},
and the posing the keyframes were posed with, /depth_fusion/posing/{camera_from_pose_frame,
pose_time,reposed_keyframes} (recorded transient local, replayed so); the input bag keeps the
ground truth (/camera/depth/image) to evaluate them against.

--map also starts map_node (docs/mapping.md): every fused keyframe is integrated into a TSDF map,
published on /depth_fusion/map/points; --save-map FILE.ply writes its mesh when the run ends (an
error, exit 1, when no map could be written).

examples:
  depth-fusion run --bag artifacts/room --record runs/room_out
  depth-fusion run --bag room --params my_params.yaml --processes --rate 0.5
  depth-fusion run --bag room --save-map runs/room_map.ply
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'run',
        help='run the ROS 2 node graph on a rosbag2 and record the fused depth',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        '--bag', required=True, type=Path, metavar='BAG', help='rosbag2 folder (or .mcap/.db3) to play'
    )
    p.add_argument(
        '--params',
        type=Path,
        metavar='FILE',
        help='ROS params file for every node (sections per node name; see config/depth_fusion.yaml)',
    )
    p.add_argument('--record', type=Path, metavar='OUT_BAG', help='record the outputs to this rosbag2 folder')
    p.add_argument(
        '--storage', choices=('mcap', 'sqlite3'), default='mcap', help='storage of --record (default mcap)'
    )
    p.add_argument(
        '--record-topic',
        action='append',
        default=[],
        metavar='TOPIC',
        help='also record this topic (repeatable; its type is taken from the graph)',
    )
    p.add_argument('--processes', action='store_true', help='run each node as its own process')
    p.add_argument(
        '--map',
        action='store_true',
        help='also start map_node: a TSDF map of the fused depth (docs/mapping.md)',
    )
    p.add_argument(
        '--save-map',
        type=Path,
        metavar='FILE.ply',
        help="write the map's mesh to FILE.ply when the run ends (implies --map)",
    )
    p.add_argument('--overwrite', action='store_true', help='replace the --save-map file if it exists')
    p.add_argument(
        '--realtime',
        action='store_true',
        help='play at the recorded rate whatever the graph does and report what it drops (default: a '
        'paced replay that waits while the graph is busy, so every keyframe is fused)',
    )
    p.add_argument(
        '--rate',
        type=float,
        help='playback speed, a multiple of the recorded rate (default: params file or 1)',
    )
    p.add_argument('--start-offset', type=float, metavar='SEC', help='skip this many seconds of the bag')
    p.add_argument(
        '--device', help="torch device of the nodes: 'cpu', 'cuda', 'cuda:1' (default: params file)"
    )
    p.add_argument(
        '--single-view',
        metavar='MODEL',
        help="single-view network: 'default', a checkpoint, or an exported model (.onnx, .pt2, TorchScript "
        '.pt) with its YAML beside it (default: params file)',
    )
    p.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='NODE.PARAM=VALUE',
        help='override one node parameter, e.g. --set multi_view_node.keyframe_every=10 (repeatable)',
    )
    p.add_argument(
        '--flush-timeout',
        type=float,
        default=60.0,
        metavar='SEC',
        help='after the bag ends, wait at most this long for the last keyframes (default 60)',
    )
    p.add_argument(
        '--threads',
        type=at_least(1, '--threads'),
        metavar='N',
        help='torch CPU threads per node (default: 1 composed, cores/3 with --processes; '
        'OMP_NUM_THREADS is respected)',
    )
    p.add_argument(
        '--log-dir', type=Path, metavar='DIR', help="with --processes: write each node's log to DIR/NODE.log"
    )
    net = p.add_argument_group('ROS domain (docs/running.md)')
    net.add_argument(
        '--domain-id',
        type=int,
        metavar='N',
        help='join ROS domain N on purpose (e.g. a live robot); default: a free private domain '
        'with localhost-only discovery, so no other graph hears this run',
    )
    net.add_argument(
        '--localhost-only',
        action='store_true',
        help='with --domain-id: discover peers on this machine only '
        '(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST)',
    )
    p.add_argument(
        '--allow-missing',
        action='store_true',
        help='run even when the bag lacks the image, camera_info or pose topic (says what is missing)',
    )
    p.set_defaults(func=run)


def options_from_args(args: argparse.Namespace):  # -> RunOptions (import kept lazy)
    from ..data.staging import check_no_unfinished_recording
    from ..nodes.graph import RunOptions
    from ..nodes.graph.isolation import check_domain_id
    from ..nodes.graph.map_output import check_map_path
    from .overrides import check_node_overrides, check_params_file, parse_overrides
    from .paths import check_new_file, check_output
    from .topic_names import check_topic_name

    if args.rate is not None and args.rate <= 0:
        raise ValueError(f'--rate must be positive, got {args.rate}')
    if args.log_dir is not None and not args.processes:
        raise ValueError('--log-dir only applies with --processes')
    if args.localhost_only and args.domain_id is None:
        raise ValueError('--localhost-only applies with --domain-id (a private run is localhost-only)')
    if args.domain_id is not None:
        check_domain_id(args.domain_id)
    overrides = parse_overrides(args.set, 'NODE')
    check_node_overrides(overrides)
    check_params_file(args.params)
    with_map = args.map or args.save_map is not None
    if 'map_node' in overrides and not with_map:
        raise ValueError('--set map_node.*: map_node is not started; add --map (or --save-map FILE.ply)')
    if args.save_map is not None:
        map_path = check_map_path(args.save_map)
        check_new_file(map_path, '--save-map', args.overwrite)
    elif args.overwrite:
        raise ValueError('--overwrite applies to --save-map, which is not given')
    if args.record is not None:
        check_output(args.record, '--record', exists_ok=False, bag=True)
        check_no_unfinished_recording(args.record)
    elif args.record_topic:
        raise ValueError(
            f'--record-topic {args.record_topic[0]}: nothing records it without --record OUT_BAG'
        )
    for topic in args.record_topic:
        check_topic_name('--record-topic', topic, node='recorder')
    if args.log_dir is not None:
        check_output(args.log_dir, '--log-dir')
    return RunOptions(
        bag=args.bag,
        params_file=args.params,
        record=args.record,
        record_storage=args.storage,
        record_extra=list(args.record_topic),
        processes=args.processes,
        realtime=args.realtime,
        rate=args.rate,
        start_offset=args.start_offset,
        device=args.device,
        single_view_model=args.single_view,
        overrides=overrides,
        flush_timeout=args.flush_timeout,
        log_dir=args.log_dir,
        threads_per_node=args.threads,
        domain_id=args.domain_id,
        localhost_only=True if args.localhost_only else None,
        allow_missing=args.allow_missing,
        map=args.map,
        save_map=args.save_map,
    )


def unrecorded_topics(result, asked: list[str]) -> list[str]:
    """One line per ``--record-topic`` the bag holds no message of, and why: a name the graph
    never published (a typo, a node not started) was once left out of the bag in silence."""
    lines = []
    for topic in dict.fromkeys(asked):
        if result.counts.get(topic, 0):
            continue
        why = (
            'no node of the graph published it'
            if topic in result.unannounced
            else 'its publisher sent nothing'
        )
        lines.append(f'--record-topic {topic}: nothing recorded ({why})')
    return lines


def run(args: argparse.Namespace) -> int:
    import sys

    from ..nodes.graph import GraphError, run_graph
    from ..nodes.graph.summary import empty_run, keyframe_summary
    from ..nodes.node_executor import executor_choice

    options = options_from_args(args)
    executor_choice()  # a bad DEPTH_FUSION_EXECUTOR is a one-line error before the graph starts
    if args.single_view is not None:
        from ..singleview.predictor import check_model

        check_model(args.single_view, args.device or 'cpu')  # one-line error before the graph starts
    mode = 'processes' if options.processes else 'composed'
    try:
        result = run_graph(options)
    except GraphError as exc:
        print(f'depth-fusion run: error: {exc}', file=sys.stderr)
        partial = exc.result
        if partial is not None:
            where = f'; partial recording (readable) in {partial.recorded}' if partial.recorded else ''
            print(
                f'stopped: {len(partial.fused)} of {len(partial.announced)} keyframes fused before '
                f'the failure ({mode}){where}',
                file=sys.stderr,
            )
        return 1
    domain = f' on ROS domain {result.domain_id}' if result.domain_id is not None else ''
    if result.interrupted:
        where = f'; partial recording in {result.recorded}' if result.recorded else ''
        print(f'interrupted: {keyframe_summary(result, mode)}{where}')
        return 130
    print(
        keyframe_summary(result, mode + domain)
        + (f'; recorded to {result.recorded}' if result.recorded else '')
    )
    if result.cpu_budget:  # where the cores went: which node holds the rate on this machine
        print(result.cpu_budget)
    if result.missing:
        print(f'{len(result.missing)} keyframe(s) without fused output (see the warning above)')
    for line in unrecorded_topics(result, options.record_extra):
        print(f'depth-fusion run: warning: {line}', file=sys.stderr)
    if options.save_map is not None:
        if result.map_error is not None:
            print(f'depth-fusion run: error: {result.map_error}', file=sys.stderr)
            return 1
        vertices, faces = result.map_size or (0, 0)
        print(f'map: {vertices} vertices, {faces} faces written to {result.map_file}')
    empty = empty_run(result)
    if empty:
        # Not exit 0 on an empty result: a script's `run && evaluate` must not go on.
        print(f'depth-fusion run: error: {empty}', file=sys.stderr)
        return 1
    return 0
