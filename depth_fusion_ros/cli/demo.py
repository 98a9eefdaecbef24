"""``depth-fusion demo``: the whole pipeline on embedded defaults, in one command."""

from __future__ import annotations

import argparse
from pathlib import Path

from .argtypes import at_least

DESCRIPTION = """\
Run the whole pipeline once, end to end, on embedded defaults:

  1. render a synthetic room with exact depth and poses (or use --sequence DIR)
  2. convert it to a rosbag2 (depth-fusion convert)
  3. play the bag through the ROS 2 node graph over DDS and record the fused depth
     (depth-fusion run: bag_replayer, multi_view_node, single_view_node, fusion_node)
  4. score the recorded output against ground truth beside TV, single-view, multi-view and
     offline fusion on the same keyframes (depth-fusion evaluate)

Writes OUT/report.md, OUT/results.json and PNG figures; intermediate bags go to OUT/work/.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'demo',
        help='the whole pipeline on a synthetic room: synth -> bag -> ROS 2 graph -> report',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument('--out', default='demo_out', help='output folder (default demo_out)')
    p.add_argument('--sequence', metavar='DIR', help='a TUM-layout folder instead of the synthetic room')
    p.add_argument('--frames', type=at_least(1, '--frames'), default=60, help='frames to use (default 60)')
    p.add_argument('--seed', type=int, default=0, help='seed of the synthetic room and the evaluation')
    p.add_argument('--parallax', choices=('high', 'low'), default='high', help='synthetic trajectory')
    p.add_argument('--processes', action='store_true', help='run each node as its own process')
    p.add_argument('--device', default='cpu', help="torch device (default cpu; 'cuda' when available)")
    p.add_argument(
        '--single-view',
        default='default',
        metavar='MODEL',
        help="network: 'default' or a model path (.onnx, .pt2, TorchScript .pt + YAML, checkpoint)",
    )
    p.add_argument('--rate', type=float, default=1.0, help='replay speed, multiple of real time (default 1)')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..demo import DemoOptions, run_demo
    from ..evaluation.report import metrics_table
    from ..singleview.predictor import check_model

    check_model(args.single_view, args.device)  # one-line error before the room is rendered
    from .paths import check_output

    check_output(args.out, '--out')  # before minutes of work, see cli/paths.py

    opts = DemoOptions(
        out=Path(args.out),
        sequence=Path(args.sequence) if args.sequence else None,
        frames=args.frames,
        seed=args.seed,
        parallax=args.parallax,
        processes=args.processes,
        device=args.device,
        single_view=args.single_view,
        rate=args.rate,
    )
    doc = run_demo(opts)
    demo = doc['demo']
    for name, seq in doc['sequences'].items():
        print(f'\n{name}: {seq["frames"]} keyframes\n')
        print(metrics_table(seq['methods']))
    print(f'\nnode graph: {demo["graph_summary"]}; steps (s): {demo["step_seconds"]}')
    if demo.get('cpu_budget'):
        print(demo['cpu_budget'])
    out = Path(args.out).resolve()
    print(f'\nreport:  {out / "report.md"}\nresults: {out / "results.json"}\nfigures: {out}/*.png')
    if 'map_ply' in demo:
        print(f'map:     {Path(demo["map_ply"]).resolve()} (mesh of the fused depth, world frame)')
    return 0
