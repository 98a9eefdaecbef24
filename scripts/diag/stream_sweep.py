"""Per-keyframe fused / single-view MAE on realistic-length causal synthetic streams.

The test bed of docs/fusion.md "Realistic-length causal streams" and "Certainty floor":
100 frames at 320x240, every 5th frame a keyframe, the filter read causally as the node
reads it, the node's fast fusion with at most 4096 points, the simulated prior:

    python scripts/diag/stream_sweep.py rooms:0-5 low_texture:0-3 rotation:1
    python scripts/diag/stream_sweep.py low_texture:0-3 --set fusion.certainty_floor=0.1
    python scripts/diag/stream_sweep.py repetitive:0-2 --synth texture_period=0.03

``rooms`` is the default synthetic world; the other names are stress cases
(data/synthetic/stress.py) stretched to the stream's length. Prints one line per stream
(mean and worst keyframe ratio, keyframes above 1) and the totals; ``--cache DIR`` keeps the
rendered streams between runs.
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np
import yaml

from depth_fusion_ros.data.synthetic import STRESS_CASES, SynthConfig, render_sequence, stress_config
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.harness import evaluate_sequence

sys.path.insert(0, str(Path(__file__).parent))
from stress_sweep import apply_sets  # the same --set handling (scripts/diag is no package)


def streams(text: str) -> list[tuple[str, int]]:
    """``rooms:0-5`` or ``low_texture:0,2``."""
    name, _, seeds = text.partition(':')
    if name != 'rooms' and name not in STRESS_CASES:
        raise argparse.ArgumentTypeError(f'unknown stream {name!r}')
    if '-' in seeds:
        lo, hi = seeds.split('-')
        return [(name, s) for s in range(int(lo), int(hi) + 1)]
    return [(name, int(s)) for s in seeds.split(',')]


def synth_overrides(items: list[str]) -> dict[str, object]:
    """``['texture_period=0.03']`` -> ``{'texture_period': 0.03}`` (values read as YAML, as ``--set``)."""
    return {name: yaml.safe_load(value) for name, _, value in (item.partition('=') for item in items)}


def config(name: str, seed: int, frames: int, synth: dict[str, object] | None = None) -> SynthConfig:
    size = {'width': 320, 'height': 240, 'frames': frames, 'seed': seed, **(synth or {})}
    return SynthConfig(**size) if name == 'rooms' else stress_config(name, **size)


def sequence(name: str, seed: int, frames: int, cache: Path | None, synth: dict[str, object] | None = None):
    tag = ''.join(f'_{k}{v:g}' for k, v in sorted((synth or {}).items()))
    path = cache / f'{name}_{seed}_{frames}{tag}.pkl' if cache else None
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    seq = render_sequence(config(name, seed, frames, synth))
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(seq))
    return seq


def node_params(sets: list[str]) -> dict[str, dict[str, object]]:
    """The node's fusion and multi-view settings, with ``--set`` overrides."""
    params: dict[str, dict[str, object]] = {
        'fusion': {'compile_kernel': False, 'mode': 'fast', 'max_points': 4096},
        'multi_view': {'method': 'filter'},
    }
    apply_sets(params, sets)
    return params


def stream_options(frames: int, stride: int, params: dict) -> EvalOptions:
    """A causal stream as the node reads it: 320x240, online neighbours, the simulated prior."""
    return EvalOptions(
        frames=frames,
        stride=stride,
        single_view='simulated',
        width=320,
        height=240,
        neighbour_mode='online',
        params=params,
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('streams', nargs='+', type=streams, help="'rooms:0-5', 'low_texture:0,2', ...")
    p.add_argument('--frames', type=int, default=100)
    p.add_argument('--stride', type=int, default=5)
    p.add_argument('--cache', type=Path, help='folder for the rendered streams')
    p.add_argument('--set', action='append', default=[], metavar='STAGE.FIELD=VALUE')
    p.add_argument(
        '--synth',
        action='append',
        default=[],
        metavar='FIELD=VALUE',
        help="a SynthConfig field of every stream, e.g. 'texture_period=0.03'",
    )
    args = p.parse_args()
    synth = synth_overrides(args.synth)
    params = node_params(args.set)
    everything: list[float] = []
    for name, seed in [s for group in args.streams for s in group]:
        seq = sequence(name, seed, args.frames, args.cache, synth)
        options = stream_options(args.frames, args.stride, params)
        result = evaluate_sequence(seq, ['single_view_simulated', 'fused'], options, show_progress=False)
        single = np.array(result.records['single_view_simulated'].all.mae_per_frame)
        fused = np.array(result.records['fused'].all.mae_per_frame)
        ratio = fused / single
        everything.extend(ratio.tolist())
        worse = [f'frame {k} {r:.3f}' for k, r in zip(result.keyframes, ratio, strict=True) if r > 1.0005]
        print(
            f'{name} {seed}: fused / single {fused.mean() / single.mean():.4f}; per keyframe mean '
            f'{ratio.mean():.4f}, worst {ratio.max():.4f}, above 1: {len(worse)} of {ratio.size}'
            + (f' ({", ".join(worse)})' if worse else ''),
            flush=True,
        )
    r = np.array(everything)
    print(f'{r.size} keyframes: mean {r.mean():.4f}, worst {r.max():.4f}, above 1: {int((r > 1.0005).sum())}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
