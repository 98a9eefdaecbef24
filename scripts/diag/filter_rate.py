"""The filter fed every frame against a stamp-rate cap (``filter.max_update_rate``), offline.

    python scripts/diag/filter_rate.py ../shared/data/tum_fr1_xyz_37 37 0 15 10

Feeds ``DepthFilter`` the first N frames of a TUM-layout sequence at the working grid, one torch
thread, keyframes every 5th frame (always fed), the frames in between only when the cap allows;
scores each keyframe's estimate from frame 10 on against the ground truth and prints, per rate
(Hz, 0 = every frame), frames fed, CPU seconds in the filter, mean good density (AbsRel <=
10 %, of all pixels), density, and the median over keyframes of the median AbsRel.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from depth_fusion_ros.data.tum import load_tum_sequence
from depth_fusion_ros.metrics import good_density
from depth_fusion_ros.multiview.filter import DepthFilter

KEYFRAME_EVERY = 5
FIRST_SCORED = 10


def run(seq, rate: float) -> str:
    f = DepthFilter(seq.camera)
    last, cpu, fed = -1e9, 0.0, 0
    goods, dens, meds = [], [], []
    for i, frame in enumerate(seq.frames):
        key = i % KEYFRAME_EVERY == 0
        if rate > 0 and not key and frame.stamp - last < 1.0 / rate - 1e-6:
            continue
        last = frame.stamp
        start = time.process_time()
        f.process(frame.gray, frame.pose)
        cpu += time.process_time() - start
        fed += 1
        if key and i >= FIRST_SCORED:
            depth, gt = f.result(frame.pose).depth, seq.gt_depth_working(i)
            valid = np.isfinite(depth) & np.isfinite(gt) & (gt > 0)
            goods.append(good_density(depth, gt))
            dens.append(valid.mean())
            meds.append(np.median(np.abs(depth[valid] - gt[valid]) / gt[valid]) if valid.any() else np.nan)
    return (
        f'{seq.name} rate {rate:g}: fed {fed}/{len(seq)}, cpu {cpu:.1f} s, '
        f'good density {np.mean(goods):.4f}, density {np.mean(dens):.4f}, '
        f'median AbsRel {np.nanmedian(meds):.4f}'
    )


def main() -> None:
    torch.set_num_threads(1)
    seq = load_tum_sequence(sys.argv[1], width=320, height=240, max_frames=int(sys.argv[2]))
    for rate in sys.argv[3:]:
        print(run(seq, float(rate)), flush=True)


if __name__ == '__main__':
    main()
