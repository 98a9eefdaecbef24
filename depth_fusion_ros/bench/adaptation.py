"""Online adaptation speed (``depth-fusion bench --only adaptation``).

Figures: optimiser steps per second of the shipped compact network at 320x240 (a batch of the
new keyframe plus ``replay_per_step`` replayed ones, sparse + photometric + smoothness
terms, two posed neighbours each), and whole keyframe updates per second with the default
``steps_per_keyframe`` and the guard's two forward passes. The last row says whether that
keeps up with 6 keyframes/s (a fast graph on a GPU). Synthetic keyframes (a rendered room),
so it needs no data; figures, never assertions.

Timing starts once the replay buffer holds ``guard_keyframes`` keyframes: from then on every
update has the same batch shapes, as in a long run (the first updates of a run have smaller
batches, and a GPU library tunes itself to each new shape once).
"""

from __future__ import annotations

import time

import numpy as np

from . import BenchOptions, BenchRow
from .single_view import _load_note, _torch_threads

TITLE = 'online self-supervised adaptation (depth_fusion_ros.adaptation)'
#: The keyframe rate the adaptation should keep up with.
TARGET_KEYFRAMES_PER_S = 6.0


def _samples(count: int):
    from ..adaptation.sample import Neighbour, make_sample
    from ..data.synthetic import SynthConfig, render_sequence

    seq = render_sequence(SynthConfig(width=320, height=240, frames=count + 2, seed=11, parallax='high'))
    out = []
    for i in range(1, count + 1):
        gt = seq.gt_depth_working(i)
        depth = np.full(gt.shape, np.nan, np.float32)
        depth[::6, ::6] = gt[::6, ::6]  # the density of the selected multi-view points (~3 %)
        score = np.where(np.isfinite(depth), 1.0, np.nan).astype(np.float32)
        f = seq.frames[i]
        nb = [Neighbour(seq.frames[j].rgb, seq.frames[j].pose) for j in (i - 1, i + 1)]
        out.append(
            make_sample(i, f.rgb, seq.camera, depth, score, select_fraction=1.0, pose=f.pose, neighbours=nb)
        )
    return out


def run(opts: BenchOptions) -> list[BenchRow]:
    import torch

    from ..adaptation.adapter import Adapter
    from ..adaptation.config import AdaptConfig

    config = AdaptConfig()
    warm = 1 + max(config.guard_keyframes, config.replay_per_step)
    timed = 3 if opts.quick else 7
    samples = _samples(warm + timed)
    threads = torch.get_num_threads() if torch.device(opts.device).type != 'cpu' else 2
    rows: list[BenchRow] = []
    with _torch_threads(threads):
        adapter = Adapter.from_spec('default', config, opts.device)
        for s in samples[:warm]:  # warm-up: allocations, every batch shape, cuDNN autotuning
            adapter.observe(s)
        sync = torch.cuda.synchronize if adapter.device.type == 'cuda' else (lambda: None)
        sync()
        start = time.perf_counter()
        steps_before = adapter.counters.steps
        for s in samples[warm:]:
            adapter.observe(s)
        sync()
        seconds = time.perf_counter() - start
        steps = adapter.counters.steps - steps_before
        updates = timed
        batch = 1 + config.replay_per_step
        where = f'{opts.device}, {threads} threads' if adapter.device.type == 'cpu' else opts.device
        rows.append(
            BenchRow(
                f'adaptation steps (batch {batch}, 320x240, photometric)',
                steps / seconds,
                'steps/s',
                _load_note(where),
            )
        )
        rate = updates / seconds
        rows.append(
            BenchRow(
                f'keyframe updates ({config.steps_per_keyframe} steps + guard)',
                rate,
                'keyframes/s',
                _load_note(f'{seconds / updates * 1e3:.0f} ms per keyframe'),
            )
        )
        keeps_up = 'keeps up' if rate >= TARGET_KEYFRAMES_PER_S else 'does not keep up'
        rows.append(
            BenchRow(
                f'vs {TARGET_KEYFRAMES_PER_S:g} keyframes/s',
                rate / TARGET_KEYFRAMES_PER_S,
                'x',
                f'{keeps_up}; when it does not, the node trains on the newest keyframes and '
                'counts the rest (adapt_queue_full)',
            )
        )
        rows.append(
            BenchRow(
                'updates rolled back by the guard',
                adapter.counters.rolled_back,
                '',
                f'of {adapter.counters.observed}',
            )
        )
    return rows
