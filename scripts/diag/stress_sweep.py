"""Fused / single-view MAE of the synthetic stress cases over many seeds (diagnostic).

The figures behind docs/multi_view.md "A minority is not evidence" and "A stream's first
keyframe" (test_guard_stress.py checks a few of these cases; this sweeps all of them):

    # offline, test_guard_stress's setting: 160x120, 7 frames, the middle keyframe
    python scripts/diag/stress_sweep.py all 0-29
    # causal (the node's view), the stream's first keyframe: 320x240, 8 frames, keyframe 5
    python scripts/diag/stress_sweep.py all 0-9 --size 320x240 --frames 8 --keyframe 5 --online \
        --set fusion.max_points=4096 --set fusion.stage1=all
    # one parameter changed
    python scripts/diag/stress_sweep.py rotation 0-29 --set filter.min_published_fraction=0.05

Prints one line per case and seed (ratio, the guard's decision) and the mean and worst.
Simulated prior, fast fusion, eager kernels, the temporal filter.
"""

from __future__ import annotations

import argparse
import sys

from depth_fusion_ros.data.synthetic import STRESS_CASES, render_sequence, stress_config
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.harness import evaluate_sequence
from depth_fusion_ros.fusion.guard import DECISIONS


def seeds(text: str) -> list[int]:
    """``0-29`` or ``2,8,29``."""
    if '-' in text:
        lo, hi = text.split('-')
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(',')]


def value(text: str) -> object:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def apply_sets(params: dict[str, dict[str, object]], items: list[str]) -> None:
    """``--set STAGE.FIELD=VALUE`` items into the stage parameters (numbers parsed)."""
    for item in items:
        key, _, text = item.partition('=')
        stage, _, field = key.partition('.')
        params.setdefault(stage, {})[field] = value(text)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('cases', help=f"comma-separated, or 'all' ({', '.join(sorted(STRESS_CASES))})")
    p.add_argument('seeds', type=seeds, help="'0-29' or '2,8,29'")
    p.add_argument('--size', default='160x120', help='WxH (default 160x120)')
    p.add_argument('--frames', type=int, default=7)
    p.add_argument('--keyframe', type=int, help='the keyframe scored (default: the middle frame)')
    p.add_argument('--online', action='store_true', help='causal filter reads, as the node (default offline)')
    p.add_argument('--set', action='append', default=[], metavar='STAGE.FIELD=VALUE')
    args = p.parse_args()
    width, height = (int(v) for v in args.size.split('x'))
    params: dict[str, dict[str, object]] = {
        'fusion': {'compile_kernel': False, 'mode': 'fast'},
        'multi_view': {'method': 'filter'},
    }
    apply_sets(params, args.set)
    names = sorted(STRESS_CASES) if args.cases == 'all' else args.cases.split(',')
    keyframe = args.frames // 2 if args.keyframe is None else args.keyframe
    ratios = []
    for name in names:
        for seed in args.seeds:
            sequence = render_sequence(
                stress_config(name, width=width, height=height, frames=args.frames, seed=seed)
            )
            options = EvalOptions(
                frames=args.frames,
                keyframes=[keyframe],
                single_view='simulated',
                width=width,
                height=height,
                neighbour_mode='online' if args.online else 'offline',
                params=params,
            )
            result = evaluate_sequence(
                sequence, ['single_view_simulated', 'fused'], options, show_progress=False
            )
            single = result.records['single_view_simulated'].all.summary()['mae']
            fused = result.records['fused'].all.summary()['mae']
            decision = DECISIONS[int(result.records['fused'].extras['decision'][0])]
            ratios.append(fused / single)
            print(f'{name} seed {seed}: fused / single {fused / single:.4f} ({decision})', flush=True)
    print(f'{len(ratios)} cases: mean {sum(ratios) / len(ratios):.6f}, worst {max(ratios):.4f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
