"""How far should a point's correction travel? Fused variants per keyframe, from one evaluation.

    python scripts/diag/reach_study.py dump OUT_DIR evaluate SEQ --stride 5 ... --methods single_view,fused
    python scripts/diag/reach_study.py table 'OUT_DIR/kf*.npz'

``dump`` runs any ``depth-fusion`` command with the evaluation's automatic fusion wrapped so
that every keyframe's single-view depth, multi-view depth, fused points Ω, fused depth and
ground truth are saved (``kfNNNN.npz``). ``table`` then scores, per keyframe and in the mean,
the fused depth as evaluated against variants of the paper's interpolation (fast mode):
the correction as it is, faded towards the single-view depth with the distance to the
*nearest* point of Ω (Gaussian, 3-16 px), and the points' global scale applied first. It also
prints the points' log-ratio statistics (global part, spread, correlation with distance),
the only evidence the fusion has. docs/fusion.md "Corrections that travel too far" has the
figures and the conclusion.
"""

from __future__ import annotations

import glob
import sys
from pathlib import Path

import numpy as np


def dump(out: Path, argv: list[str]) -> int:
    import depth_fusion_ros.evaluation.methods.fusion as fm
    from depth_fusion_ros.cli.main import main
    from depth_fusion_ros.evaluation.methods.multi_view import multi_view_result

    out.mkdir(parents=True, exist_ok=True)
    original = fm.fuse_automatic

    def saving(ctx, single, kind, stage3=None, **forced):
        res = original(ctx, single, kind, stage3=stage3, **forced)
        np.savez(
            out / f'kf{ctx.index:04d}.npz',
            single=single,
            mv=multi_view_result(ctx).depth,
            omega=res.omega_mask,
            fused=res.depth,
            gt=ctx.gt_depth_working,
        )
        return res

    fm.fuse_automatic = saving
    return main(argv)


def _variants(s: np.ndarray, mv: np.ndarray, om: np.ndarray, fused: np.ndarray) -> dict[str, np.ndarray]:
    from scipy.ndimage import distance_transform_edt

    from depth_fusion_ros.fusion.interpolation import interpolate

    nearest = distance_transform_edt(~om)
    offset = interpolate(s, mv, om, mode='fast').offset
    scale = float(np.exp(np.median(np.log(mv[om] / s[om]))))
    scaled_offset = interpolate(scale * s, mv, om, mode='fast').offset
    out = {'single': s, 'fused (as evaluated)': fused, 'paper, no reach': s + offset}
    for sd in (3, 5, 8, 16):
        out[f'nearest-point reach {sd} px'] = s + np.exp(-0.5 * (nearest / sd) ** 2) * offset
    for sd in (8, 16):
        out[f'global scale + reach {sd} px'] = scale * s + np.exp(-0.5 * (nearest / sd) ** 2) * scaled_offset
    return out


def table(pattern: str) -> int:
    scores: dict[str, list[float]] = {}
    for name in sorted(glob.glob(pattern)):
        d = np.load(name)
        s, mv, om, fused, gt = d['single'], d['mv'], d['omega'], d['fused'], d['gt']
        if om.sum() == 0:
            continue
        ok = np.isfinite(gt) & (gt > 0) & np.isfinite(fused) & np.isfinite(s)
        r = np.log(mv[om] / s[om])
        g = float(np.median(r))
        spread = float(np.std(r - g))
        print(f'{Path(name).stem}: |Ω| {int(om.sum())}, points log(m/s) median {g:+.2f}, spread {spread:.2f}')
        for label, depth in _variants(s, mv, om, fused).items():
            valid = ok & np.isfinite(depth)
            scores.setdefault(label, []).append(float(np.mean(np.abs(depth - gt)[valid])))
    if not scores:
        print(f'no keyframe with points in {pattern}')
        return 1
    single = np.array(scores['single'])
    print(f'{len(single)} keyframes with points')
    for label, values in scores.items():
        ratio = np.array(values) / single
        print(
            f'  {label:30s} MAE {np.mean(values):.4f} m, worse than single view on '
            f'{int((ratio > 1.0001).sum())}/{len(ratio)} (max ratio {ratio.max():.3f})'
        )
    return 0


if __name__ == '__main__':
    if len(sys.argv) >= 3 and sys.argv[1] == 'dump':
        raise SystemExit(dump(Path(sys.argv[2]), sys.argv[3:]))
    if len(sys.argv) == 3 and sys.argv[1] == 'table':
        raise SystemExit(table(sys.argv[2]))
    raise SystemExit(__doc__)
