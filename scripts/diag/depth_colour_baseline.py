"""Where a dataset's colour camera sits beside its depth camera, read from the images alone
(diagnostic): the centre at which the ground-truth depth's edges, registered into the colour
camera, land on the colour image's edges.

Why: 7-Scenes gives a Kinect's depth on the depth camera's grid and publishes no extrinsics
between its two cameras. Registered as if both had one optical centre, a near object's
outline lands pixels off where the colour image shows it (docs/data.md). No depth estimate of
the project is used here, so the answer does not lean towards the estimator being scored:
for each candidate centre, the registered depth's edges (a jump of more than 10 % in log depth
between neighbouring pixels) are scored by the colour image's gradient under them, relative
to the frame's mean gradient. The centre where they line up scores highest.

    python scripts/diag/depth_colour_baseline.py ../shared/data/7scenes_redkitchen_000_499 \\
        --rgb-camera config/cameras/7scenes_rgb.yaml

Prints one line per candidate centre (x, y in metres, z 0) and the best one.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np

from depth_fusion_ros.data.depth_registration import register_depth
from depth_fusion_ros.data.tum import load_tum_sequence, read_camera_yaml

#: A depth edge: neighbouring pixels more than this apart in log depth.
EDGE_LOG_DEPTH = 0.1


def edge_contrast(depth: np.ndarray, gradient: np.ndarray) -> float | None:
    """The colour gradient on ``depth``'s edges over the frame's mean gradient (``None`` where
    the frame has too few edges)."""
    log_depth = np.log(np.where(depth > 0, depth, np.nan))
    edge = np.zeros(depth.shape, dtype=bool)
    with np.errstate(invalid='ignore'):
        across = np.abs(np.diff(log_depth, axis=1)) > EDGE_LOG_DEPTH
        down = np.abs(np.diff(log_depth, axis=0)) > EDGE_LOG_DEPTH
    edge[:, 1:] |= across
    edge[:, :-1] |= across
    edge[1:, :] |= down
    edge[:-1, :] |= down
    return float(gradient[edge].mean() / gradient.mean()) if edge.sum() >= 50 else None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('sequence', type=Path, help='TUM-layout folder whose camera.yaml is the depth camera')
    p.add_argument('--rgb-camera', type=Path, required=True, help='the colour camera YAML')
    p.add_argument('--frames', type=int, default=500)
    p.add_argument('--step', type=int, default=10, help='score every step-th frame')
    p.add_argument('--x', type=float, nargs='+', default=[-0.025, 0.0, 0.015, 0.025, 0.035, 0.05])
    p.add_argument('--y', type=float, nargs='+', default=[-0.01, 0.0, 0.01, 0.02, 0.03])
    args = p.parse_args()
    colour = read_camera_yaml(args.rgb_camera)
    colour = dataclasses.replace(colour, centre_in_depth_camera=(0.0, 0.0, 0.0))
    native = colour.camera
    # The colour images at their own size; the depth on the depth camera's own grid.
    images = load_tum_sequence(
        args.sequence, native.width, native.height, args.frames, rgb_calibration=colour
    ).frames[:: args.step]
    depths = load_tum_sequence(args.sequence, native.width, native.height, args.frames)
    depth_camera = depths.gt_camera
    frames = []
    for image, depth in zip(images, depths.frames[:: args.step], strict=True):
        grey = image.gray.astype(np.float32)
        gradient = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
        frames.append((depth.depth, gradient))
    best = None
    for x in args.x:
        for y in args.y:
            scores = [
                edge_contrast(register_depth(d, depth_camera, native, (x, y, 0.0)), g) for d, g in frames
            ]
            scores = [s for s in scores if s is not None]
            if not scores:
                raise SystemExit(f'{args.sequence}: no frame has depth edges to score')
            score = float(np.mean(scores))
            print(f'centre x {x:+.3f} m, y {y:+.3f} m: edge contrast {score:.3f} ({len(scores)} frames)')
            if best is None or score > best[0]:
                best = (score, x, y)
    print(f'best: centre_in_depth_camera: [{best[1]}, {best[2]}, 0.0] (edge contrast {best[0]:.3f})')


if __name__ == '__main__':
    main()
