"""Mapping benchmark: TSDF integration time per 320x240 keyframe at 4 cm voxels, memory.

A synthetic room (the project's own renderer) seen along its trajectory; every keyframe's
exact depth is integrated with a uniform confidence. Targets: ≤ 20 ms per keyframe on 2 CPU
cores, ≤ 2 ms on an H100 (``--device cuda``). Also: mesh extraction time, blocks, the storage
the map holds and its cap (``max_blocks``), and the Open3D engine when it is installed.
Figures, never assertions; the machine load is in the notes.
"""

from __future__ import annotations

import os
import statistics
import time

import numpy as np
import torch

from ..data.synthetic import SynthConfig, render_sequence
from ..mapping.config import MapConfig
from ..mapping.engine import make_map
from ..mapping.open3d_tsdf import open3d_available
from . import BenchOptions, BenchRow

TITLE = 'mapping (TSDF integration and surface extraction)'


def _sync(device: str) -> None:
    if device.startswith('cuda'):
        torch.cuda.synchronize()


def _engine_rows(engine_name: str, seq, opts: BenchOptions) -> list[BenchRow]:
    config = MapConfig(engine=engine_name, voxel_size=0.04, device=opts.device)
    tsdf, note = make_map(config)
    if tsdf.name != engine_name:
        return [BenchRow(f'{engine_name}: not run', float('nan'), '', note)]
    confidence = np.full((seq.camera.height, seq.camera.width), 0.8, np.float32)
    times = []
    for i, frame in enumerate(seq.frames):
        depth = seq.gt_depth_working(i)
        _sync(opts.device)
        t0 = time.perf_counter()
        tsdf.integrate(depth, frame.pose, seq.camera, confidence=confidence, rgb=frame.rgb)
        _sync(opts.device)
        times.append(time.perf_counter() - t0)
    # The first calls allocate and warm up (and with the consistency test's lag of
    # config.consistency_span keyframes, only queue): every later call integrates one keyframe,
    # its consistency test included.
    steady = times[2:] if len(times) > 4 else times
    tsdf.flush()
    t0 = time.perf_counter()
    mesh = tsdf.mesh()
    extract = time.perf_counter() - t0
    load = f'load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores, {torch.get_num_threads()} torch threads'
    size = (
        f'{seq.camera.width}x{seq.camera.height}, {len(seq)} keyframes, {opts.device}, '
        f'consistency test against {2 * config.consistency_span} keyframes included'
    )
    tag = f'{engine_name} on {opts.device}'
    median_ms = 1e3 * statistics.median(steady)
    mesh_note = f'{len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles'
    cap = f'cap {config.max_blocks * config.bytes_per_block / 2**20:.0f} MiB'
    return [
        BenchRow(f'{tag}: integrate ms/keyframe (median)', median_ms, 'ms', f'{size}; {load}'),
        BenchRow(f'{tag}: integrate ms/keyframe (max)', 1e3 * max(steady), 'ms', size),
        BenchRow(f'{tag}: mesh extraction', extract, 's', mesh_note),
        BenchRow(f'{tag}: voxel blocks', float(tsdf.n_blocks), 'blocks', f'cap {config.max_blocks}'),
        BenchRow(f'{tag}: map storage', tsdf.memory_bytes / 2**20, 'MiB', cap),
    ]


def run(opts: BenchOptions) -> list[BenchRow]:
    frames = 6 if opts.quick else 30
    seq = render_sequence(SynthConfig(width=320, height=240, frames=frames, seed=1))
    rows = _engine_rows('torch', seq, opts)
    if open3d_available() is None:
        rows += _engine_rows('open3d', seq, opts)
    else:
        rows.append(BenchRow('open3d: not installed', float('nan'), '', 'optional engine (docs/mapping.md)'))
    return rows
