"""Do the told poses agree with the images? Epipolar error of the poses against the images' own.

    python scripts/diag/pose_epipolar.py TUM_DIR [--gap 5] [--frames 100]

For frame pairs ``gap`` apart (every second frame), ORB features are matched at 640x480 and
the images' own essential matrix is fitted (RANSAC, 1 px). Over its inlier matches the median
Sampson distance is printed twice: under the told relative pose (groundtruth.txt and
camera.yaml) and under the fitted matrix, which is the floor the matching itself sets. Told
poses as consistent as the images give about the floor; a pose source with per-frame errors
gives more. Only the error across the epipolar lines is seen: a pose error that moves the
points along them (a time offset on a smooth path, a wrong focal length on a sideways sweep)
is not. What it found: docs/multi_view.md, "Told poses against the images".
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from depth_fusion_ros.data.tum import load_tum_sequence
from depth_fusion_ros.geometry import relative_pose
from depth_fusion_ros.multiview.epipolar_cost import sampson_distances, skew
from depth_fusion_ros.multiview.image_pairs import image_features, rigid_matches


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('path')
    p.add_argument('--gap', type=int, default=5, help='frames between the two images of a pair')
    p.add_argument('--frames', type=int, default=100)
    args = p.parse_args()
    seq = load_tum_sequence(args.path, width=640, height=480, max_frames=args.frames)
    K = seq.camera.K
    Ki = np.linalg.inv(K)
    orb = cv2.ORB_create(3000)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    feats = [image_features(orb, f.gray) for f in seq.frames]
    told, own = [], []
    for i in range(0, len(seq.frames) - args.gap, 2):
        matched = rigid_matches(matcher, K, feats[i], feats[i + args.gap], 8)
        if matched is None:
            continue
        p1, p2, E = matched
        T = relative_pose(seq.frames[i].pose, seq.frames[i + args.gap].pose)
        F_told = Ki.T @ skew(T[:3, 3]) @ T[:3, :3] @ Ki
        told.append(float(np.median(np.abs(sampson_distances(F_told, p1, p2)))))
        own.append(float(np.median(np.abs(sampson_distances(Ki.T @ E @ Ki, p1, p2)))))
        pair = f'{i:3d} -> {i + args.gap}: {len(p1):4d} matches'
        print(f'{pair}, told pose {told[-1]:.2f} px, own {own[-1]:.2f} px')
    if not told:
        raise SystemExit(f'{args.path}: no frame pair could be matched')
    print(
        f"median over {len(told)} pairs (640x480): told poses {np.median(told):.2f} px, the images' own "
        f'geometry {np.median(own):.2f} px ({np.median(told) / np.median(own):.1f}x)'
    )


if __name__ == '__main__':
    main()
