"""Online adaptation speed (``depth-fusion bench --only adaptation``).

Figures: optimiser steps per second of the shipped compact network at 320x240 (a batch of the
new keyframe plus ``replay_per_step`` replayed ones, sparse + photometric + smoothness
terms, two posed neighbours each), and whole keyframe updates per second with the default
``steps_per_keyframe`` and the guard's two forward passes. The last row says whether that
keeps up with 6 keyframes/s (a fast graph on a GPU), and the rate of the shorter updates a node
makes while behind (``steps_when_behind``). Synthetic keyframes (a rendered room),
so it needs no data; figures, never assertions.

Timing starts once the replay buffer holds ``guard_keyframes`` accepted keyframes, and three
updates after that: from then on every update has the same batch shapes, as in a long run.
The first updates of a run have smaller batches and a GPU library prepares its kernels for
each new shape once, which on an H200 took 2-9 s an update (``scripts/diag/adapt_update_times.py``,
docs/performance.md "GPU"); counting warm-up by keyframes observed, as this bench did until
2026-11-27, timed two such updates whenever the guard rolled one back during warm-up (a
rolled-back keyframe does not enter the buffer): 1.15 s a keyframe against 0.2 s steady. The
slowest warm-up update is its own row.
"""

from __future__ import annotations

import time

import numpy as np

from . import BenchOptions, BenchRow, load_note
from .single_view import _torch_threads

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


#: Most keyframes observed before timing (a guard that rolls back many updates fills the
#: buffer slowly; timing starts anyway after these, and the row says how full it was).
WARM_MAX = 16
#: Updates observed once the buffer is full, before timing: the guard's first full-size
#: evaluations and the replay's full draws happen in them.
WARM_AFTER_FULL = 3


def _warm_up(adapter, samples: list, full: int, sync) -> tuple[int, float]:
    """Observe ``samples`` until the buffer holds ``full`` accepted keyframes and
    ``WARM_AFTER_FULL`` more updates ran: (keyframes used, slowest update in seconds)."""
    after_full, slowest = 0, 0.0
    for i, s in enumerate(samples):
        sync()
        t0 = time.perf_counter()
        adapter.observe(s)
        sync()
        slowest = max(slowest, time.perf_counter() - t0)
        if len(adapter.buffer) >= full:
            after_full += 1
            if after_full > WARM_AFTER_FULL:
                return i + 1, slowest
    return len(samples), slowest


def _observe_seconds(adapter, samples: list, sync, behind: bool = False) -> float:
    """Wall-clock seconds of observing ``samples`` one after the other (device synchronised)."""
    sync()
    start = time.perf_counter()
    for s in samples:
        adapter.observe(s, behind=behind)
    sync()
    return time.perf_counter() - start


def run(opts: BenchOptions) -> list[BenchRow]:
    import torch

    from ..adaptation.adapter import Adapter
    from ..adaptation.config import AdaptConfig

    config = AdaptConfig()
    full = max(config.guard_keyframes, config.replay_per_step)  # buffer size of the full batch shapes
    timed = 3 if opts.quick else 7
    samples = _samples(WARM_MAX + 2 * timed)
    threads = torch.get_num_threads() if torch.device(opts.device).type != 'cpu' else 2
    rows: list[BenchRow] = []
    with _torch_threads(threads):
        adapter = Adapter.from_spec('default', config, opts.device)
        sync = torch.cuda.synchronize if adapter.device.type == 'cuda' else (lambda: None)
        warm, slowest = _warm_up(adapter, samples[:WARM_MAX], full, sync)
        steps_before = adapter.counters.steps
        seconds = _observe_seconds(adapter, samples[warm : warm + timed], sync)
        steps = adapter.counters.steps - steps_before
        updates = timed
        batch = 1 + config.replay_per_step
        where = f'{opts.device}, {threads} threads' if adapter.device.type == 'cpu' else opts.device
        rows.append(
            BenchRow(
                f'adaptation steps (batch {batch}, 320x240, photometric)',
                steps / seconds,
                'steps/s',
                load_note(where),
            )
        )
        rate = updates / seconds
        rows.append(
            BenchRow(
                f'keyframe updates ({config.steps_per_keyframe} steps + guard)',
                rate,
                'keyframes/s',
                load_note(f'{seconds / updates * 1e3:.0f} ms per keyframe'),
            )
        )
        behind_rate = timed / _observe_seconds(adapter, samples[warm + timed : warm + 2 * timed], sync, True)
        rows.append(
            BenchRow(
                f'keyframe updates while behind ({config.steps_when_behind} steps + guard)',
                behind_rate,
                'keyframes/s',
                load_note(
                    f'{1e3 / behind_rate:.0f} ms per keyframe; what a node that cannot keep up makes '
                    '(docs/adaptation.md, "On a CPU budget")'
                ),
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
                'slowest warm-up update (first use of a batch shape)',
                slowest,
                's',
                f'{warm} warm-up keyframes until the buffer held {full} (not timed above)',
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
