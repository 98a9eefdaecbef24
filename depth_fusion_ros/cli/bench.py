"""``depth-fusion bench``: speed and memory figures of every stage."""

from __future__ import annotations

import argparse
import importlib
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    from ..bench import SECTIONS

    p = sub.add_parser(
        'bench',
        help='measure speed and memory of each stage and print the figures',
        description='Benchmarks (figures, not pass/fail): multi-view keyframes/s, TV s/keyframe, '
        'CNN inference Hz, fusion exact/fast timing, node-graph throughput and latency.',
    )
    p.add_argument(
        '--only', default=','.join(SECTIONS), help=f'comma-separated sections ({", ".join(SECTIONS)})'
    )
    p.add_argument('--device', default='cpu', help="torch device (default cpu; 'cuda' when available)")
    p.add_argument('--quick', action='store_true', help='smoke run with small inputs (not a measurement)')
    p.add_argument('--repeats', type=int, default=5, help='timed repetitions per figure (default 5)')
    p.add_argument(
        '--sequence',
        action='append',
        default=[],
        metavar='SEQ_DIR',
        help='TUM folder for sections that measure on real data (repeatable)',
    )
    p.add_argument('--json', metavar='FILE', help='also write the figures as JSON')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..bench import BenchOptions

    opts = BenchOptions(device=args.device, quick=args.quick, repeats=args.repeats, sequences=args.sequence)
    out: dict[str, list[dict]] = {}
    for name in [s.strip() for s in args.only.split(',') if s.strip()]:
        try:
            module = importlib.import_module(f'depth_fusion_ros.bench.{name}')
        except ModuleNotFoundError:
            print(f'bench section {name!r} is not available', file=sys.stderr)
            continue
        print(f'## {module.TITLE}', flush=True)
        rows = module.run(opts)
        for r in rows:
            note = f'  ({r.note})' if r.note else ''
            print(f'  {r.name:48s} {r.value:12.4g} {r.unit}{note}', flush=True)
        out[name] = [vars(r) for r in rows]
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(out, f, indent=2)
    return 0
