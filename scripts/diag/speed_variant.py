"""A TUM-layout folder whose camera moves K times faster at the same frame rate.

Why: the real sequences here move slowly (7-Scenes about 0.2 m/s), and a robot or a walking
hand moves faster. Keeping every K-th colour frame and compressing every stamp by K (poses,
depth and colour alike) gives the same camera at the same frame rate moving K times as fast:
K times the baseline and the turn between frames, and K times the pose speed the pose-jump
test sees. Everything is linked, not copied (nothing from ../shared/data is duplicated).

    python scripts/diag/speed_variant.py ../shared/data/7scenes_redkitchen_000_499 /tmp/7s_fast3 --every 3
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from held_variant import read_list, write_list


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('source', type=Path, help='a TUM-layout folder (rgb.txt, depth.txt, groundtruth.txt)')
    p.add_argument('out', type=Path, help='the folder to write (must not exist)')
    p.add_argument('--every', type=int, required=True, help='keep every K-th colour frame (K >= 2)')
    args = p.parse_args(argv)
    src, out, k = args.source.resolve(), args.out, args.every
    if k < 2:
        raise SystemExit('speed_variant: --every must be >= 2')
    rgb_c, rgb = read_list(src / 'rgb.txt')
    dep_c, dep = read_list(src / 'depth.txt')
    gt_c, gt = read_list(src / 'groundtruth.txt')
    t0 = rgb[0][0]

    def squeeze(rows):
        return [(t0 + (t - t0) / k, f) for t, f in rows]

    kept = rgb[::k]
    depth = sorted({min(range(len(dep)), key=lambda j: abs(dep[j][0] - t)) for t, _ in kept})
    out.mkdir(parents=True)
    for entry in src.iterdir():
        if entry.name not in ('rgb.txt', 'depth.txt', 'groundtruth.txt'):
            os.symlink(entry, out / entry.name)
    write_list(out / 'rgb.txt', rgb_c, squeeze(kept))
    write_list(out / 'depth.txt', dep_c, squeeze([dep[j] for j in depth]))
    write_list(out / 'groundtruth.txt', gt_c, squeeze(gt))
    print(f'{out}: {len(kept)} of {len(rgb)} frames, the motion {k}x as fast')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
