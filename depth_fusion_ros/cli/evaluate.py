"""``depth-fusion evaluate``: score depth methods against ground truth on TUM-layout folders or
rosbag2s (a robot's own recording: its topics and the camera's mount are options)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import at_least
from .recordings import given_topics, topic_arguments

#: The paper's evaluation: Table II columns, the oracle, the Table III ablation, Table I inputs.
PAPER_METHODS = (
    'tv',
    'single_view',
    'multi_view',
    'multi_view_selected',
    'fused',
    'fused_oracle',
    'fused_w1',
    'fused_w1w2',
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'evaluate',
        help='score depth methods on TUM-layout sequences or rosbag2s (results.json, report.md, figures)',
        description='Run registered depth methods on the first N frames of each sequence and '
        'compare them with the ground-truth depth (paper §IV). Writes OUT/results.json and '
        'OUT/report.md and prints the table. A sequence is a TUM-layout folder or a rosbag2 with '
        'colour, camera_info, poses and depth registered to the colour camera (the topics of '
        "depth-fusion convert, or a robot's own: the options below).",
    )
    p.add_argument(
        'sequences', nargs='*', metavar='SEQ_DIR', help='TUM-layout folder(s) or rosbag2 folder(s)'
    )
    p.add_argument(
        '--methods',
        default=','.join(PAPER_METHODS),
        help="comma-separated method names (see --list); default: the paper's full set",
    )
    p.add_argument('--list', action='store_true', help='list the available methods and exit')
    p.add_argument(
        '--frames',
        type=at_least(1, '--frames'),
        default=100,
        help='use the first N frames (default 100, as the paper)',
    )
    p.add_argument(
        '--stride',
        type=at_least(1, '--stride'),
        default=None,
        help='every k-th of those frames is a keyframe (default 1)',
    )
    p.add_argument(
        '--recorded-keyframes',
        action='store_true',
        help='the keyframes are the frames the recording of --set recorded.bag=PATH holds fused depth '
        "for (the graph's keyframes, as the demo scores them): graph_* and offline methods on one set",
    )
    p.add_argument(
        '--single-view',
        default='default',
        metavar='SRC',
        help="single-view source: 'default' (shipped model), a model path (.onnx, .pt2, TorchScript .pt "
        "with its YAML, or a checkpoint), 'simulated' (the simulated CNN prior) or 'simulated_relative' "
        '(it as inverse depth up to an unknown scale and shift per keyframe)',
    )
    p.add_argument(
        '--neighbours', type=at_least(1), default=4, help='overlapping frames per keyframe (default 4)'
    )
    p.add_argument(
        '--neighbour-mode',
        choices=('offline', 'online'),
        default='offline',
        help='offline: window around the keyframe; online: past frames only (as the node)',
    )
    p.add_argument('--width', type=at_least(16), default=320, help='working width (default 320)')
    p.add_argument('--height', type=at_least(16), default=240, help='working height (default 240)')
    p.add_argument('--device', default='cpu', help="torch device: 'cpu', 'cuda', 'cuda:0' (default cpu)")
    p.add_argument('--seed', type=int, default=0, help='seed of every random choice (default 0)')
    p.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='STAGE.KEY=VALUE',
        help='override a stage parameter, e.g. --set fusion.mode=fast, or --set multi_view.method=sweep '
        "for the paper's multi-view sweep instead of the default temporal filter (repeatable)",
    )
    p.add_argument(
        '--rgb-camera',
        action='append',
        default=[],
        metavar='[SEQ_NAME=]YAML',
        help='colour-camera calibration for a sequence whose camera.yaml is the depth camera '
        '(7-Scenes: config/cameras/7scenes_rgb.yaml); the depth is registered into it (repeatable). '
        "For a rosbag2: used instead of its camera_info (its depth must be the colour camera's)",
    )
    topic_arguments(p, depth=True)
    p.add_argument('--out', default='eval_out', help='output folder (default eval_out)')
    p.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    p.set_defaults(func=run)


def parse_rgb_cameras(items: list[str]) -> dict[str, str]:
    """``['seq=cam.yaml', 'all.yaml']`` -> ``{'seq': 'cam.yaml', '*': 'all.yaml'}``."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, path = item.rpartition('=')
        out[name if sep else '*'] = path
    return out


def recording_topics(args: argparse.Namespace) -> dict[str, str]:
    """The topic options given, checked before any data is loaded: they name a rosbag2's topics,
    so at least one of the sequences must be one (a ``ValueError`` naming them otherwise)."""
    from ..data.bag_recovery import readable_rosbag2

    topics = given_topics(args)
    if topics and not any(readable_rosbag2(s) for s in args.sequences):
        named = ', '.join('--' + name.replace('_', '-') for name in topics)
        raise ValueError(f'{named}: topics are for a rosbag2, and no SEQ_DIR is one')
    return topics


def check_recorded(methods: list[str], params: dict, recorded_keyframes: bool, stride: int | None) -> None:
    """The recorded graph's methods and ``--recorded-keyframes`` need the bag, named before
    any data loads (they said so only at the first keyframe); ``--stride`` and
    ``--recorded-keyframes`` choose the keyframes two ways, so both is an error."""
    from ..evaluation.methods.recorded import recorded_bag

    graph = [m for m in methods if m.startswith('graph_')]
    bag = params.get('recorded', {}).get('bag')
    if graph or recorded_keyframes:
        bag = recorded_bag(params.get('recorded', {}), graph[0] if graph else '--recorded-keyframes')
    if bag and not Path(str(bag)).exists():
        raise FileNotFoundError(f'recorded.bag {bag}: no such bag')
    if recorded_keyframes and stride is not None:
        raise ValueError('--stride and --recorded-keyframes both choose the keyframes: give one')


def run(args: argparse.Namespace) -> int:
    from ..evaluation.context import EvalOptions
    from ..evaluation.harness import evaluate_sequences
    from ..evaluation.registry import available_methods, get_method
    from ..evaluation.report import report_markdown
    from ..singleview.predictor import check_model
    from .overrides import check_stage_overrides, parse_overrides
    from .paths import check_output

    if args.list:
        for name, spec in available_methods().items():
            print(f'{name:24s} {spec.description}')
        return 0
    if not args.sequences:
        raise ValueError('give at least one TUM-layout folder or rosbag2 (SEQ_DIR), or --list')
    methods = [m.strip() for m in args.methods.split(',') if m.strip()]
    if not methods:
        raise ValueError(f'--methods {args.methods!r} names no method (see --list)')
    for name in methods:  # a typo fails before the model loads
        get_method(name)
    check_model(args.single_view, args.device, allow_simulated=True)  # before any data is loaded
    params = parse_overrides(args.set, 'STAGE')
    check_stage_overrides(params)  # a typo fails now, not after minutes of evaluation
    check_recorded(methods, params, args.recorded_keyframes, args.stride)
    check_output(args.out, '--out')
    options = EvalOptions(
        frames=args.frames,
        stride=args.stride or 1,
        recorded_keyframes=args.recorded_keyframes,
        seed=args.seed,
        device=args.device,
        single_view=args.single_view,
        neighbour_mode=args.neighbour_mode,
        num_neighbours=args.neighbours,
        width=args.width,
        height=args.height,
        params=params,
        rgb_cameras=parse_rgb_cameras(args.rgb_camera),
        topics=recording_topics(args),
        camera_from_pose_frame=args.camera_from_pose_frame,
    )
    doc = evaluate_sequences(args.sequences, methods, options, args.out, figures=not args.no_figures)
    print(report_markdown(doc))
    print(f'wrote {args.out}/results.json and {args.out}/report.md')
    return 0
