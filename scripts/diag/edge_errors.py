"""Where the filter's wrong estimates are: at depth edges, and with which side's depth (figures).

    python scripts/diag/edge_errors.py TUM_DIR

Runs ``DepthFilter`` over the first 80 frames of a TUM-layout folder at 320x240 and, every
fifth frame from frame 20 on, takes every published estimate with ground truth. An estimate is
*wrong* when it is more than 10 % off, *at a depth edge* when the ground truth within 3 px
(a 7x7 window) spans more than 10 % (max / min), and *foreground* when it is within 5 % of the
nearest depth in that window (the occluding side's depth given to a pixel of the occluded side:
the "fattening" of window matching at occlusion boundaries). Prints the shares. What it found
on issue 11's stress cases and the real sequences: docs/multi_view.md, "Where the wrong
estimates are".
"""

from __future__ import annotations

import sys

import cv2
import numpy as np

from depth_fusion_ros.data.tum import load_tum_sequence
from depth_fusion_ros.multiview.filter import DepthFilter


def main(path: str) -> None:
    seq = load_tum_sequence(path, width=320, height=240, max_frames=80)
    f = DepthFilter(seq.camera)
    window = np.ones((7, 7), np.uint8)
    rows = []
    for i, frame in enumerate(seq.frames):
        f.process(frame.gray, frame.pose)
        if i < 20 or i % 5:
            continue
        result, gt = f.result(frame.pose), seq.gt_depth_working(i)
        g = np.where(np.isfinite(gt) & (gt > 0), gt, np.nan).astype(np.float32)
        nearest = cv2.erode(np.nan_to_num(g, nan=1e6), window)
        farthest = cv2.dilate(np.nan_to_num(g, nan=0.0), window)
        ok = np.isfinite(result.depth) & np.isfinite(g)
        wrong = np.abs(result.depth - g) / g > 0.1
        edge = farthest / nearest > 1.1
        foreground = np.abs(result.depth - nearest) / nearest < 0.05
        rows.append(np.stack([wrong[ok], edge[ok], foreground[ok]], 1))
    if not rows:
        raise SystemExit(f'{path}: fewer than 21 frames, nothing scored')
    wrong, edge, foreground = np.concatenate(rows).astype(bool).T
    print(f'published estimates scored: {wrong.size}; wrong (> 10 % off): {wrong.mean():.3f}')
    print(
        f'at a depth edge: {edge.mean():.3f} of all; wrong there {wrong[edge].mean():.3f}, elsewhere '
        f'{wrong[~edge].mean():.3f}'
    )
    print(
        f'of the wrong ones: {edge[wrong].mean():.3f} at an edge, and of those '
        f'{foreground[wrong & edge].mean():.3f} with the foreground depth'
    )


if __name__ == '__main__':
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    main(sys.argv[1])
