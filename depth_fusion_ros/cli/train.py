"""``depth-fusion train``: train the compact or the Eigen network on TUM-layout folders."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from .argtypes import at_least

EPILOG = """\
examples:
  depth-fusion train artifacts/synth/seq_* --out runs/compact --steps 3000
  depth-fusion train SEQ... --arch eigen --device cuda --batch-size 16 --out runs/eigen
  depth-fusion train SEQ... --out runs/compact --resume          # continue runs/compact/last.pt
  depth-fusion train SEQ... --out runs/compact --ship model.pt   # also write a small fp16 copy

Outputs in --out: last.pt (resumable), best.pt (lowest validation MAE), history.json, curve.png.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'train',
        help='train a single-view depth network on TUM-layout folders',
        description='Train the compact encoder-decoder or the Eigen & Fergus three-scale network on '
        'TUM-layout folders (undistorted and resized; ground truth from the depth images) with the '
        'scale-invariant + gradient loss, zoom-crop/flip/colour augmentation and a validation split '
        'scored with the project metrics.',
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument('sequences', nargs='+', metavar='SEQ_DIR', help='TUM-layout training folder(s)')
    p.add_argument('--out', default='runs/train', help='output folder (default runs/train)')
    p.add_argument(
        '--arch', choices=('compact', 'eigen'), default='compact', help='network (default compact)'
    )
    p.add_argument(
        '--arch-config',
        action='append',
        default=[],
        metavar='KEY=VALUE',
        help='architecture field, e.g. --arch-config fc_dim=1024 (repeatable; YAML values)',
    )
    p.add_argument(
        '--val', action='append', default=[], metavar='SEQ_DIR', help='validation folder (repeatable)'
    )
    p.add_argument(
        '--val-fraction',
        type=float,
        default=0.1,
        help='without --val: hold out this fraction of the folders (or of the frames of a single folder)',
    )
    p.add_argument(
        '--frames', type=at_least(1, '--frames'), default=None, help='use the first N frames of each folder'
    )
    p.add_argument('--every', type=at_least(1), default=1, help='use every k-th frame (default 1)')
    p.add_argument('--steps', type=at_least(1), default=2000, help='optimiser steps (default 2000)')
    p.add_argument('--batch-size', type=at_least(1), default=8, help='images per step (default 8)')
    p.add_argument(
        '--lr', type=float, default=1e-3, help='peak learning rate (AdamW, cosine decay; default 1e-3)'
    )
    p.add_argument('--weight-decay', type=float, default=1e-4)
    p.add_argument('--si-lambda', type=float, default=0.5, help='λ of the scale-invariant loss (default 0.5)')
    p.add_argument('--grad-weight', type=float, default=1.0, help='weight of the gradient term (default 1)')
    p.add_argument('--max-zoom', type=float, default=1.25, help='largest zoom-crop factor (1 = off)')
    p.add_argument('--jitter', type=float, default=0.2, help='colour jitter amount (0 = off)')
    p.add_argument('--no-flip', action='store_true', help='no horizontal flips')
    p.add_argument('--val-every', type=at_least(1), default=200, help='validate and checkpoint every N steps')
    p.add_argument('--val-max-samples', type=at_least(1), default=120, help='validate on at most N images')
    p.add_argument('--seed', type=int, default=0, help='seed of every random choice (default 0)')
    p.add_argument('--device', default='cpu', help="torch device: 'cpu', 'cuda', 'cuda:0' (default cpu)")
    p.add_argument(
        '--threads', type=at_least(1), default=None, help='torch CPU threads (default: torch decides)'
    )
    p.add_argument('--resume', action='store_true', help='continue OUT/last.pt')
    p.add_argument(
        '--ship', metavar='PATH', help='after training, write best.pt as a small fp16 checkpoint (+ .yaml)'
    )
    p.add_argument(
        '--overwrite', action='store_true', help='replace the --ship file and its YAML if they exist'
    )
    p.add_argument('--no-progress', action='store_true', help='no progress bar')
    p.set_defaults(func=run)


def parse_arch_config(items: list[str]) -> dict[str, object]:
    import yaml

    out: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition('=')
        if not sep or not key:
            raise ValueError(f'--arch-config expects KEY=VALUE, got {item!r}')
        out[key.strip()] = yaml.safe_load(value)
    return out


def source_summary(path: str | Path) -> str:
    """The title line of a folder's SOURCE.md (provenance recorded in the model's metadata)."""
    source = Path(path) / 'SOURCE.md'
    if source.is_file():
        for line in source.read_text().splitlines():
            if line.strip():
                return line.lstrip('# ').strip()
    return 'unknown (no SOURCE.md)'


def check_training_outputs(args: argparse.Namespace) -> None:
    """Every output checked before the data loads: a finished run in ``--out`` is kept unless
    ``--resume`` continues it, and ``--ship`` replaces a file only with ``--overwrite``."""
    from .paths import check_new_model, check_output

    out = check_output(args.out, '--out')
    last = out / 'last.pt'
    if args.resume and not last.is_file():
        raise FileNotFoundError(f'--resume: {last} does not exist')
    if not args.resume and last.exists():
        raise ValueError(
            f'--out {out} holds a training run ({last}): pass --resume to continue it, or choose '
            'another folder'
        )
    if args.ship:
        check_new_model(args.ship, '--ship', args.overwrite)
    elif args.overwrite:
        raise ValueError('--overwrite applies to --ship, which is not given')


def run(args: argparse.Namespace) -> int:
    import torch

    from ..singleview.architectures import arch_input_size
    from ..singleview.augment import AugmentConfig
    from ..singleview.training import TrainConfig, ship_checkpoint, train_model
    from ..singleview.training_data import DepthSamples, load_folder_samples, split_validation

    if args.threads:
        torch.set_num_threads(args.threads)
    arch_config = parse_arch_config(args.arch_config)
    width, height = arch_input_size(args.arch, arch_config)
    for folder in [*args.sequences, *args.val]:
        if not Path(folder).is_dir():
            raise FileNotFoundError(f'training folder not found: {folder}')
    check_training_outputs(args)

    def load(folder: str) -> DepthSamples:
        return load_folder_samples(folder, width, height, args.frames, args.every)

    per_sequence = [load(f) for f in args.sequences]
    if args.val:
        train = DepthSamples.concat(per_sequence)
        val = DepthSamples.concat([load(f) for f in args.val])
    else:
        train, val = split_validation(per_sequence, args.val_fraction)
    cfg = TrainConfig(
        architecture=args.arch,
        arch_config=arch_config,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        weight_decay=args.weight_decay,
        si_lambda=args.si_lambda,
        grad_weight=args.grad_weight,
        augment=AugmentConfig(max_zoom=args.max_zoom, flip=not args.no_flip, jitter=args.jitter),
        val_every=args.val_every,
        val_max_samples=args.val_max_samples,
        seed=args.seed,
        device=args.device,
    )
    info = {
        'command': shlex.join(['depth-fusion', *sys.argv[1:]]) if sys.argv else '',
        # SOURCE.md titles of every folder given (training and validation split): provenance.
        'training_sources': sorted({source_summary(f) for f in args.sequences}),
        'validation_sequences': list(val.sequences),
        'validation_samples': len(val),
    }
    result = train_model(
        train, val, cfg, args.out, resume=args.resume, show_progress=not args.no_progress, extra_info=info
    )
    for h in result.history:
        v = h.get('val', {})
        print(
            f'step {h["step"]:6d}  train loss {h["train_loss"]:.4f}  '
            + (
                f'val loss {v["loss"]:.4f}  MAE {v["mae"]:.3f} m  si {v["si"]:.4f}  δ1 {v["delta1"]:.3f}'
                if v
                else ''
            )
        )
    print(f'wrote {result.last_path}' + (f' and {result.best_path}' if result.best_path else ''))
    if args.ship:
        src = result.best_path or result.last_path
        path = ship_checkpoint(src, args.ship)
        size_mb = path.stat().st_size / 1e6
        print(f'shipped {src} as {path} ({size_mb:.2f} MB) and {path.with_suffix(".yaml")}')
    return 0
