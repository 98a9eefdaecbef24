"""Synthetic sequence rendering speed (``depth-fusion bench --only synthetic``)."""

from __future__ import annotations

import os
import tempfile
import time

from . import BenchOptions, BenchRow, load_note

TITLE = 'synthetic sequences (numpy ray casting, depth_fusion_ros.data.synthetic)'


def run(opts: BenchOptions) -> list[BenchRow]:
    """Time scene building, in-memory rendering and TUM writing at 640x480.

    Full mode renders the 100-frame default sequence; quick mode 10 frames. Rendering is
    numpy on the CPU, so ``opts.device`` does not apply.
    """
    from ..data.synthetic import SynthConfig, build_world, iter_frames, write_synthetic_sequence

    frames = 10 if opts.quick else 100
    cfg = SynthConfig(width=640, height=480, frames=frames, seed=0)
    rows: list[BenchRow] = []

    start = time.perf_counter()
    scene, trajectory = build_world(cfg)
    rows.append(BenchRow('scene build (layout + textures)', time.perf_counter() - start, 's'))

    start = time.perf_counter()
    for _ in iter_frames(cfg, scene, trajectory):
        pass
    render = time.perf_counter() - start
    rows.append(BenchRow('render 640x480', render / frames, 's/frame', load_note()))
    rows.append(BenchRow(f'render {frames} frames 640x480', render, 's'))

    with tempfile.TemporaryDirectory(prefix='bench_synth_') as tmp:
        start = time.perf_counter()
        write_synthetic_sequence(os.path.join(tmp, 'seq'), cfg)
        total = time.perf_counter() - start
    rows.append(BenchRow(f'synth {frames} frames to TUM folder (total)', total, 's', load_note()))
    rows.append(BenchRow('synth to TUM folder', total / frames, 's/frame'))
    return rows
