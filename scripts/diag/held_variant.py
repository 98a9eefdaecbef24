"""A TUM-layout folder whose camera stands still for a while: a robot that stops (at a door, in
a queue, for an operator) and a hand-held camera put down, then moved on.

Why: a stop is the most common thing a real robot does, and the graph has only ever been fed
streams that keep moving. While the camera stands, every frame is the same view with new sensor
noise, and the keyframe policy, the filter, the adaptation's replay buffer and the map keep
receiving it. This makes any real TUM folder so, for the live client
(`scripts/diag/live_client.py`) or `evaluate`.

    python scripts/diag/held_variant.py ../shared/data/7scenes_redkitchen_000_499 /tmp/7s_held \
        --at 150 --hold 300 --noise 2

Frame ``--at`` is held for ``--hold`` more frames at the sequence's frame rate: each held frame
is that colour image with its own Gaussian noise (``--noise`` grey levels; 0: the same file),
its depth the same file and its pose the same pose. Every later frame and pose is moved by the
hold's duration. Nothing from the source is copied except the held frames' noisy images, which
are written to the output folder (keep it out of the project).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import cv2
import numpy as np


def read_list(path: Path) -> tuple[list[str], list[tuple[float, list[str]]]]:
    """A TUM list file: its comment lines and its (stamp, fields) rows."""
    comments, rows = [], []
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith('#'):
            comments.append(line)
            continue
        fields = line.split()
        rows.append((float(fields[0]), fields[1:]))
    return comments, rows


def write_list(path: Path, comments: list[str], rows: list[tuple[float, list[str]]]) -> None:
    path.write_text('\n'.join([*comments, *(' '.join([f'{t:.6f}', *f]) for t, f in rows)]) + '\n')


def shifted(rows: list[tuple[float, list[str]]], after: float, by: float) -> list[tuple[float, list[str]]]:
    """Rows at or after ``after`` moved ``by`` seconds later; the others as they are."""
    return [(t + by if t >= after else t, f) for t, f in rows]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('source', type=Path, help='a TUM-layout folder (rgb.txt, depth.txt, groundtruth.txt)')
    p.add_argument('out', type=Path, help='the folder to write (must not exist)')
    p.add_argument('--at', type=int, required=True, help='index of the colour frame the camera stops at')
    p.add_argument('--hold', type=int, required=True, help='held frames added after it')
    p.add_argument('--noise', type=float, default=2.0, help='sensor noise of each held image (grey levels)')
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args(argv)
    src, out = args.source.resolve(), args.out
    rgb_c, rgb = read_list(src / 'rgb.txt')
    dep_c, dep = read_list(src / 'depth.txt')
    gt_c, gt = read_list(src / 'groundtruth.txt')
    if not 0 <= args.at < len(rgb) - 1 or args.hold < 1:
        raise SystemExit(f'held_variant: --at must lie in 0..{len(rgb) - 2} and --hold be >= 1')
    t_at, (name_at,) = rgb[args.at][0], rgb[args.at][1][:1]
    period = (rgb[-1][0] - rgb[0][0]) / (len(rgb) - 1)
    hold_s = args.hold * period
    after = (t_at + rgb[args.at + 1][0]) / 2  # everything after the held frame moves
    held_t = [t_at + (k + 1) * period for k in range(args.hold)]
    out.mkdir(parents=True)
    for entry in src.iterdir():
        if entry.name not in ('rgb.txt', 'depth.txt', 'groundtruth.txt'):
            os.symlink(entry, out / entry.name)
    rng = np.random.default_rng(args.seed)
    image = cv2.imread(str(src / name_at), cv2.IMREAD_UNCHANGED).astype(np.float32)
    (out / 'held').mkdir()
    new_rgb = []
    for k, t in enumerate(held_t):
        if args.noise > 0:
            name = f'held/{k:05d}.png'
            noisy = np.clip(np.round(image + rng.normal(0.0, args.noise, image.shape)), 0, 255)
            cv2.imwrite(str(out / name), noisy.astype(np.uint8))
        else:
            name = name_at
        new_rgb.append((t, [name]))
    d_at = min(dep, key=lambda r: abs(r[0] - t_at))
    g_at = min(gt, key=lambda r: abs(r[0] - t_at))
    held_dep = [(t + d_at[0] - t_at, d_at[1]) for t in held_t]
    held_gt = [(t, g_at[1]) for t in held_t]
    for name, comments, rows, held in (
        ('rgb.txt', rgb_c, rgb, new_rgb),
        ('depth.txt', dep_c, dep, held_dep),
        ('groundtruth.txt', gt_c, gt, held_gt),
    ):
        write_list(out / name, comments, sorted(shifted(rows, after, hold_s) + held, key=lambda r: r[0]))
    print(f'{out}: frame {args.at} ({t_at:.3f} s) held for {args.hold} frames ({hold_s:.2f} s)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
