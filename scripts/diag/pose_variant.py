"""A TUM-layout folder whose poses are given the way a misconfigured pose source gives them.

Why: the judges' robots publish poses we never see, and two conventions go wrong often: a
body frame's pose (REP 103, x forward) given as the camera's, and the world's pose in the
camera (T_cw, a SLAM system's own) given as the camera's in the world. `depth-fusion synth
--pose-frame body|inverted` makes synthetic streams so; this makes any real TUM folder so,
for the live client (`scripts/diag/live_client.py`) or `evaluate`. Everything but
`groundtruth.txt` is linked, not copied (nothing from ../shared/data is duplicated).

    python scripts/diag/pose_variant.py ../shared/data/tum_fr1_xyz_37 /tmp/tum_inverted --as inverted
    python scripts/diag/pose_variant.py ../shared/data/tum_fr1_xyz_37 /tmp/tum_body --as body

`scaled` (``--scale K``): the positions multiplied by K, as a monocular SLAM gives them (its
unit is whatever its initialisation chose); score the result against depth in those units
(``live_client.py --depth-factor F/K``).

`body`: T_told = T_cam @ M^-1 (M = geometry.BODY_TO_OPTICAL, the camera in the body frame);
`camera_from_pose_frame [0, 0, 0, -0.5, 0.5, -0.5, 0.5]` turns it back. `inverted`: T_told =
T_cam^-1; `pose_inverted: true` reads it right.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from depth_fusion_ros.geometry import BODY_TO_OPTICAL

VARIANTS = ('body', 'inverted', 'scaled')


def told_pose(T: np.ndarray, variant: str, scale: float = 1.0) -> np.ndarray:
    """The camera-to-world pose ``T`` (4x4) as the misconfigured source gives it."""
    if variant == 'scaled':
        out = T.copy()
        out[:3, 3] *= scale
        return out
    if variant == 'inverted':
        return np.linalg.inv(T)
    M = np.eye(4)
    M[:3, :3] = BODY_TO_OPTICAL
    return T @ np.linalg.inv(M)


def rewrite_line(line: str, variant: str, scale: float = 1.0) -> str:
    """One groundtruth.txt line (``stamp tx ty tz qx qy qz qw``) rewritten; comments as they are."""
    fields = line.split()
    if not fields or line.startswith('#'):
        return line
    values = [float(v) for v in fields[1:8]]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(values[3:]).as_matrix()
    T[:3, 3] = values[:3]
    out = told_pose(T, variant, scale)
    q = Rotation.from_matrix(out[:3, :3]).as_quat()
    return ' '.join([fields[0], *(f'{x:.6f}' for x in out[:3, 3]), *(f'{x:.7f}' for x in q)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('source', type=Path, help='a TUM-layout folder (groundtruth.txt, rgb.txt, ...)')
    p.add_argument('out', type=Path, help='the folder to write (must not exist)')
    p.add_argument('--as', dest='variant', choices=VARIANTS, required=True, help='how the poses are given')
    p.add_argument('--scale', type=float, default=0.5, help='scaled: the positions multiplied by this')
    args = p.parse_args(argv)
    if args.variant == 'scaled' and not (np.isfinite(args.scale) and args.scale > 0):
        p.error(f'--scale must be a positive number, got {args.scale}')
    source = args.source.resolve()
    truth = source / 'groundtruth.txt'
    if not truth.is_file():
        p.error(f'{truth}: no groundtruth.txt (a TUM-layout folder is needed)')
    if args.out.exists():
        p.error(f'{args.out} exists: choose a new folder')
    args.out.mkdir(parents=True)
    for name in os.listdir(source):
        if name != 'groundtruth.txt':
            os.symlink(source / name, args.out / name)
    lines = [rewrite_line(line, args.variant, args.scale) for line in truth.read_text().splitlines()]
    (args.out / 'groundtruth.txt').write_text('\n'.join(lines) + '\n')
    print(f'wrote {args.out}: {source.name} with its poses given as {args.variant}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
