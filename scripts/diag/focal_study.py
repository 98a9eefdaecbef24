"""The shipped network's depth on cameras with other focal lengths (docs/single_view.md).

    python scripts/diag/focal_study.py

Unseen synthetic rooms (seeds 3, 5, 7; frames 0 and 2 of 4; 320x240) rendered with 0.5x to 2x
the network's training focal length: per scale, the median depth / truth per seed, the MAE of
the depth as it is, the MAE after the Metric3D-style factor ``f / f_train`` (tried and not
kept), and the MAE of a constant (each frame's median truth).
"""

from __future__ import annotations

import numpy as np

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.singleview.checkpoint import load_checkpoint
from depth_fusion_ros.singleview.predictor import default_model_path, load_predictor


def main() -> None:
    predictor = load_predictor('default')
    focal = float(load_checkpoint(default_model_path()).metadata.info['training_focal_px'])
    print(
        'focal / training | median depth / truth (seeds 3, 5, 7) | MAE as it is | '
        'MAE x f/f_train | MAE constant'
    )
    for scale in (0.5, 0.75, 1.0, 1.33, 2.0):
        ratios, raw, scaled, const = [], [], [], []
        for seed in (3, 5, 7):
            f = focal * scale
            seq = render_sequence(SynthConfig(width=320, height=240, frames=4, seed=seed, fx=f, fy=f))
            per_seed = []
            for i in (0, 2):
                gt = seq.gt_depth_working(i)
                ok = np.isfinite(gt) & (gt > 0)
                depth = predictor.predict(seq.frames[i].rgb)
                per_seed.append(np.median(depth[ok] / gt[ok]))
                raw.append(np.mean(np.abs(depth - gt)[ok]))
                scaled.append(np.mean(np.abs(depth * scale - gt)[ok]))
                const.append(np.mean(np.abs(np.median(gt[ok]) - gt[ok])))
            ratios.append(np.mean(per_seed))
        print(
            f'{scale} | {", ".join(f"{r:.2f}" for r in ratios)} | {np.mean(raw):.3f} | '
            f'{np.mean(scaled):.3f} | {np.mean(const):.3f}'
        )


if __name__ == '__main__':
    main()
