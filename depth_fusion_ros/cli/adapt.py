"""``depth-fusion adapt``: adapt a single-view network to posed sequences offline, self-supervised.

The same code as the node's online adaptation and the evaluation's ``single_view_adapted``
(``evaluation.methods.adapted.adapted_prediction``): keyframes in order, the multi-view search
of each against its neighbours, the fusion's verdict on its points, then one guarded update on
its selected multi-view points and its photometric consistency with the posed neighbours
(none where the fusion's guard trusted none of the points). Ground-truth depth is never read for
training: no depth is read (folders without depth images, a robot's rosbag2 with its own
topics). Writes a checkpoint that ``--single-view`` / ``model:`` load.
"""

from __future__ import annotations

import argparse
import sys

from .argtypes import at_least
from .recordings import topic_arguments


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'adapt',
        help='adapt the single-view network to posed sequences, self-supervised (writes a checkpoint)',
        description='Train the single-view network on TUM-layout folders or rosbag2s without ground truth: '
        'multi-view depth of the selected points and photometric consistency with posed '
        'neighbours, with replay and a held-out guard (docs/adaptation.md). Writes --out, a '
        'checkpoint that --single-view and the node parameter model: load.',
    )
    p.add_argument(
        'sequences', nargs='+', metavar='SEQ_DIR', help='TUM-layout folder(s) or rosbag2 folder(s), in order'
    )
    p.add_argument('--out', required=True, metavar='CKPT', help='checkpoint to write (.pt)')
    p.add_argument('--overwrite', action='store_true', help='replace CKPT if it exists')
    p.add_argument(
        '--model',
        default='default',
        help="network to start from: 'default' or a checkpoint (default: default)",
    )
    p.add_argument(
        '--frames',
        type=at_least(1),
        default=None,
        help='use the first N frames of each sequence (default all)',
    )
    p.add_argument('--stride', type=at_least(1), default=1, help='every k-th frame is a keyframe (default 1)')
    p.add_argument(
        '--neighbours', type=at_least(1), default=4, help='overlapping frames per keyframe (default 4)'
    )
    p.add_argument(
        '--neighbour-mode',
        choices=('offline', 'online'),
        default='online',
        help='online: past frames only, as the node (default); offline: a window around the keyframe',
    )
    p.add_argument('--width', type=at_least(16), default=320, help='working width (default 320)')
    p.add_argument('--height', type=at_least(16), default=240, help='working height (default 240)')
    p.add_argument('--device', default='cpu', help='torch device (default cpu)')
    p.add_argument('--seed', type=int, default=0, help='seed (default 0)')
    p.add_argument('--threads', type=at_least(0), default=0, help='torch threads (default: torch decides)')
    p.add_argument(
        '--set',
        action='append',
        default=[],
        metavar='STAGE.KEY=VALUE',
        help='override a parameter, e.g. --set adaptation.lr=1e-4 or --set multi_view.num_samples=64',
    )
    p.add_argument(
        '--rgb-camera',
        action='append',
        default=[],
        metavar='[SEQ_NAME=]YAML',
        help='colour-camera calibration for a sequence whose camera.yaml is the depth camera (7-Scenes)',
    )
    topic_arguments(p, depth=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from ..evaluation.context import EvalOptions, KeyframeContext
    from ..evaluation.harness import load_evaluation_sequence
    from ..evaluation.methods.adapted import adaptation_run, adapted_prediction
    from ..progress import progress
    from .evaluate import parse_rgb_cameras, recording_topics
    from .overrides import parse_overrides
    from .paths import check_new_file

    # before minutes of adaptation: a checkpoint already there is someone's result (cli/paths.py)
    check_new_file(args.out, '--out', args.overwrite)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    options = EvalOptions(
        frames=args.frames,
        stride=args.stride,
        seed=args.seed,
        device=args.device,
        single_view=args.model,
        neighbour_mode=args.neighbour_mode,
        num_neighbours=args.neighbours,
        width=args.width,
        height=args.height,
        params=parse_overrides(args.set, 'STAGE'),
        rgb_cameras=parse_rgb_cameras(args.rgb_camera),
        topics=recording_topics(args),
        camera_from_pose_frame=args.camera_from_pose_frame,
    )
    run_state = None
    for path in args.sequences:
        seq = load_evaluation_sequence(path, options, with_depth=False)
        shared = {} if run_state is None else {'adaptation:run': run_state}
        keyframes = range(0, len(seq), max(1, args.stride))
        for i in progress(keyframes, desc=seq.name, unit='kf'):
            ctx = KeyframeContext(seq, i, options, shared)
            adapted_prediction(ctx)  # predicted, fused (the guard's trust), then trained on
            run_state = adaptation_run(ctx)
    if run_state is None:
        raise ValueError('the sequences hold no keyframe')
    c = run_state.adapter.counters
    summary = (
        f'{c.observed} keyframes: {c.updated} updates, {c.rolled_back} rolled back by the guard, '
        f'{c.skipped} skipped {dict(c.reasons) or ""}, {c.steps} steps in {c.train_seconds:.1f} s'
    )
    if c.updated == 0:
        raise ValueError(f'no update was kept, nothing to write ({summary})')
    out = run_state.adapter.save(
        args.out, {'sequences': [str(s) for s in args.sequences], 'command': ' '.join(sys.argv)}
    )
    print(summary)
    print(f'wrote {out} (use it with --single-view {out} or the node parameter model:={out})')
    return 0
