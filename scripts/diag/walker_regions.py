"""Fused / single-view MAE on a walker's pixels and on the static rest (diagnostic, figures only).

    python scripts/diag/walker_regions.py 0,1,2 [--set STAGE.FIELD=VALUE ...] [--cache DIR]

Renders the ``moving_object`` stress stream of each seed (data/synthetic/stress.py: the
lateral sweep with a person-sized box walking across the view) as ``stream_sweep.py`` does
(320x240, 100 frames, every 5th a keyframe, the filter read causally, the node's fast
fusion, the simulated prior), and the same room without the walker: the pixels whose depth
differs are the walker's. Each region is scored alone by blanking the other's ground truth.
Prints per seed and region the mean single-view and fused MAE, their ratio, and how many
keyframes the fusion made worse there (docs/fusion.md, "A known limit: moving objects").
"""

from __future__ import annotations

import argparse
import copy
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from depth_fusion_ros.data.synthetic import render_sequence
from depth_fusion_ros.evaluation.harness import evaluate_sequence

sys.path.insert(0, str(Path(__file__).parent))
import stream_sweep  # the same streams and --set handling (scripts/diag is no package)


def walker_masks(seed: int, seq) -> list[np.ndarray]:
    """Per frame, the pixels where the walker stands (nearer than the same room without it)."""
    static = render_sequence(replace(stream_sweep.config('moving_object', seed, len(seq.frames)), walkers=0))
    return [f.depth < s.depth - 1e-3 for f, s in zip(seq.frames, static.frames, strict=True)]


def region_line(seq, masks: list[np.ndarray], inside: bool, params: dict) -> str:
    """Single-view and fused MAE scored on the walker (``inside``) or on the rest only."""
    scored = copy.copy(seq)
    scored.frames = [
        replace(f, depth=np.where(m if inside else ~m, f.depth, 0.0).astype(f.depth.dtype))
        for f, m in zip(seq.frames, masks, strict=True)
    ]
    options = stream_sweep.stream_options(len(seq.frames), 5, params)
    result = evaluate_sequence(scored, ['single_view_simulated', 'fused'], options, show_progress=False)
    single = np.array(result.records['single_view_simulated'].all.mae_per_frame, dtype=float)
    fused = np.array(result.records['fused'].all.mae_per_frame, dtype=float)
    ok = np.isfinite(single) & np.isfinite(fused) & (single > 0)
    ratio = fused[ok] / single[ok]
    return (
        f'{"walker" if inside else "static"}: single {single[ok].mean():.3f} fused {fused[ok].mean():.3f} '
        f'(x{fused[ok].mean() / single[ok].mean():.2f}), keyframes worse {int((ratio > 1.0005).sum())} '
        f'of {int(ok.sum())}, worst x{ratio.max():.2f}'
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('seeds', help='comma-separated seeds, e.g. 0,1,2')
    p.add_argument('--cache', type=Path, help='folder for the rendered streams')
    p.add_argument('--set', action='append', default=[], metavar='STAGE.FIELD=VALUE')
    args = p.parse_args()
    params = stream_sweep.node_params(args.set)
    for seed in (int(s) for s in args.seeds.split(',')):
        seq = stream_sweep.sequence('moving_object', seed, 100, args.cache)
        masks = walker_masks(seed, seq)
        share = np.mean([m.mean() for m in masks])
        lines = [region_line(seq, masks, inside, params) for inside in (True, False)]
        print(f'seed {seed} (the walker on {share:.0%} of the pixels): ' + ' | '.join(lines), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
