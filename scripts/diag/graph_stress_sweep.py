"""The synthetic stress cases through the whole node graph, as a user runs it (diagnostic).

What the other sweeps (``stress_sweep.py``, ``stream_sweep.py``) do not cover: the defaults a
user gets (the shipped network adapted online, the checks in correct mode, the graph's own
keyframe policy and timing), the conversion to a bag and the DDS graph in between. Each case:

    depth-fusion synth DIR/seq --stress CASE --frames N --seed S --width 320 --height 240
    depth-fusion convert DIR/seq DIR/bag
    depth-fusion run --bag DIR/bag --record DIR/rec               # composed, paced, defaults
    depth-fusion evaluate DIR/seq --frames N --methods graph_fused,graph_single_view,graph_multi_view \
        --set recorded.bag=DIR/rec --neighbour-mode online --out DIR/eval

and prints one line: fused and single-view MAE of what the graph published, their ratio, the
worst keyframe's ratio and how many keyframes were fused above their input, the multi-view
MAE, the run's summary and the node's own check verdicts (from its log). The fusion's
decisions are recorded too, and ``DIR/keyframes.jsonl`` holds one line per keyframe: its
fused / single ratio beside the guard's decision and evidence (which evidence would have told
a keyframe fused above its input):

    python scripts/diag/graph_stress_sweep.py translation rotation keyframes --seed 21 --out /tmp/gs
    python scripts/diag/graph_stress_sweep.py all --seed 21 --out /tmp/gs      # every stress case
    python scripts/diag/graph_stress_sweep.py keyframes --seed 71 --out /tmp/gs \
        --synth '--focal-error 0.05 --gain-sigma 0.1' --tag slam               # a case with more stressors
    python scripts/diag/graph_stress_sweep.py handheld --seed 21 --out /tmp/gs --tag _off \
        --synth '--pose-scale 0.3' --run-set fusion_node.stream_scale.mode=off  # a node parameter set

docs/fusion.md "The stress cases through the node graph" holds the figures.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

from depth_fusion_ros.data.synthetic import STRESS_CASES

CHECK_LINES = re.compile(r'(focal length check|time offset check|mount check): ([^(;]*)')


def run(args: list[str], log: Path) -> None:
    """One CLI step, its output to ``log``; a failure stops this case with the log's tail."""
    with log.open('w') as out:
        done = subprocess.run(
            [sys.executable, '-m', 'depth_fusion_ros.cli.main', *args], stdout=out, stderr=out
        )
    if done.returncode != 0:
        tail = log.read_text().splitlines()[-3:]
        raise RuntimeError(f'{args[0]} failed ({done.returncode}): ' + ' | '.join(tail))


def node_checks(log: Path) -> str:
    """The node's check verdicts, as its log says them (first words of each line)."""
    said = {name: text.strip()[:40] for name, text in CHECK_LINES.findall(log.read_text())}
    return '; '.join(f'{name}: {text}' for name, text in said.items()) or 'no check finished'


def score(results: Path) -> str:
    seq = next(iter(json.loads(results.read_text())['sequences'].values()))
    m = seq['methods']
    fused, single = m['graph_fused'], m['graph_single_view']
    ratios = [
        a / b
        for a, b in zip(fused['per_frame_mae'], single['per_frame_mae'], strict=True)
        if a is not None and b
    ]
    above = sum(r > 1.0 for r in ratios)
    return (
        f'fused {fused["mae"]:.3f} single {single["mae"]:.3f} ratio {fused["mae"] / single["mae"]:.3f} '
        f'worst keyframe {max(ratios):.3f} above {above}/{len(ratios)} '
        f'multi-view {m["graph_multi_view"]["mae"]:.3f}'
    )


def keyframe_lines(results: Path, seq: Path, rec: Path, topic: str, out: Path) -> None:
    """One JSON line per scored keyframe: fused / single ratio, decision and the guard's evidence,
    matched by stamp (``seq``'s rgb.txt gives each frame's); a keyframe without a recorded
    decision gets ``"decision": null``."""
    from rosbags.highlevel import AnyReader

    lines = (seq / 'rgb.txt').read_text().splitlines()
    stamps = [float(line.split()[0]) for line in lines if line[:1] != '#']
    scored = next(iter(json.loads(results.read_text())['sequences'].values()))
    fused, single = scored['methods']['graph_fused'], scored['methods']['graph_single_view']
    with AnyReader([rec]) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        said = [json.loads(reader.deserialize(raw, c.msgtype).data) for c, _, raw in reader.messages(conns)]
    by_stamp = {round(d['stamp'], 3): d for d in said}
    with out.open('w') as f:
        for frame, (a, b) in enumerate(zip(fused['per_frame_mae'], single['per_frame_mae'], strict=True)):
            if a is None or not b:
                continue
            d = by_stamp.get(round(stamps[frame], 3))
            line = {'frame': frame, 'ratio': round(a / b, 4), 'decision': d and d['decision']}
            f.write(json.dumps({**line, **(d['evidence'] if d else {})}) + '\n')


def sweep_case(
    case: str, seed: int, frames: int, out: Path, synth: list[str], tag: str, run_set: list[str] | None = None
) -> str:
    d = out / f'{case}_{seed}{tag}'
    d.mkdir(parents=True, exist_ok=True)
    for old in ('seq', 'bag', 'rec', 'eval'):
        subprocess.run(['rm', '-rf', str(d / old)], check=True)
    size = ['--width', '320', '--height', '240']
    run(
        [
            'synth',
            str(d / 'seq'),
            '--stress',
            case,
            '--frames',
            str(frames),
            '--seed',
            str(seed),
            *size,
            '--quiet',
            *synth,
        ],
        d / 'synth.log',
    )
    run(['convert', str(d / 'seq'), str(d / 'bag')], d / 'convert.log')
    decisions = '/depth_fusion/fused/decision'
    run(
        [
            'run',
            '--bag',
            str(d / 'bag'),
            '--record',
            str(d / 'rec'),
            '--record-topic',
            decisions,
            *(arg for item in run_set or () for arg in ('--set', item)),
        ],
        d / 'run.log',
    )
    methods = 'graph_fused,graph_single_view,graph_multi_view'
    run(
        [
            'evaluate',
            str(d / 'seq'),
            '--frames',
            str(frames),
            '--methods',
            methods,
            '--set',
            f'recorded.bag={d / "rec"}',
            '--neighbour-mode',
            'online',
            '--out',
            str(d / 'eval'),
        ],
        d / 'eval.log',
    )
    summary = next(
        line for line in (d / 'run.log').read_text().splitlines()[::-1] if 'keyframes chosen' in line
    )
    scored = score(d / 'eval' / 'results.json')
    keyframe_lines(d / 'eval' / 'results.json', d / 'seq', d / 'rec', decisions, d / 'keyframes.jsonl')
    return f'{case + tag:16s} {scored} | {summary[:48]} | {node_checks(d / "run.log")}'


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument('cases', nargs='+', help=f'stress cases, or all ({", ".join(STRESS_CASES)})')
    parser.add_argument('--seed', type=int, default=21)
    parser.add_argument('--frames', type=int, default=100)
    parser.add_argument('--out', type=Path, required=True, help='working folder (one subfolder per case)')
    parser.add_argument(
        '--synth', default='', help="more `depth-fusion synth` flags after the case's own, one quoted string"
    )
    parser.add_argument('--tag', default='', help='suffix of the case folders and lines (runs with --synth)')
    parser.add_argument(
        '--run-set',
        action='append',
        default=[],
        metavar='NODE.PARAM=VALUE',
        help='a node parameter for `depth-fusion run --set` (repeatable; use with --tag)',
    )
    args = parser.parse_args()
    cases = list(STRESS_CASES) if args.cases == ['all'] else args.cases
    unknown = [c for c in cases if c not in STRESS_CASES]
    if unknown:
        parser.error(f'unknown stress case(s) {", ".join(unknown)}')
    failed = 0
    for case in cases:
        try:
            line = sweep_case(
                case, args.seed, args.frames, args.out, shlex.split(args.synth), args.tag, args.run_set
            )
            print(line, flush=True)
        except (RuntimeError, StopIteration, KeyError, ValueError) as exc:
            failed += 1
            print(f'{case + args.tag:16s} FAILED: {exc}', flush=True)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
