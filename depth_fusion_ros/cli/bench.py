"""``depth-fusion bench``: speed and memory figures of every stage."""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path


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


def chosen_sections(only: str) -> list[str]:
    """The sections ``--only`` names, in its order; ``ValueError`` (one line, with a
    did-you-mean) for a name that is not one, or for none at all: a bench that measures
    nothing must not end as if it had."""
    from ..bench import SECTIONS
    from .overrides import did_you_mean

    names = [s.strip() for s in only.split(',') if s.strip()]
    if not names:
        raise ValueError(f'--only names no section (sections: {", ".join(SECTIONS)})')
    for name in names:
        if name not in SECTIONS:
            hint = did_you_mean(name, SECTIONS)
            raise ValueError(f'--only {name}: no such bench section{hint} (sections: {", ".join(SECTIONS)})')
    return names


def run(args: argparse.Namespace) -> int:
    from ..bench import BenchOptions
    from .paths import check_output

    names = chosen_sections(args.only)
    if args.repeats < 1:
        raise ValueError(f'--repeats must be at least 1, got {args.repeats}')
    for folder in args.sequence:
        if not Path(folder).is_dir():
            raise FileNotFoundError(f'--sequence {folder}: no such folder')
    if args.json:
        check_output(args.json, '--json', folder=False)
    opts = BenchOptions(device=args.device, quick=args.quick, repeats=args.repeats, sequences=args.sequence)
    out: dict[str, list[dict]] = {}
    for name in names:
        module = importlib.import_module(f'depth_fusion_ros.bench.{name}')
        print(f'## {module.TITLE}', flush=True)
        rows = module.run(opts)
        for r in rows:
            note = f'  ({r.note})' if r.note else ''
            print(f'  {r.name:48s} {r.value:12.4g} {r.unit}{note}', flush=True)
        if not rows:
            print('  (no figures)', flush=True)
        out[name] = [vars(r) for r in rows]
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(out, f, indent=2)
    if not any(out.values()):
        print('depth-fusion bench: no section gave a figure', file=sys.stderr)
        return 1
    return 0
