"""Single-view CNN inference speed (``depth-fusion bench --only single_view``).

Targets: the compact model at >= 10 Hz for a 320x240 image on 2 CPU cores; the Eigen &
Fergus network's inference time measured; the shipped network under ONNX Runtime, torch.export
and eager torch (``model_hosts.py``). Figures are ``DepthPredictor.predict`` end to
end (resize, normalise, network, resize back), the median of ``repeats`` runs after a
warm-up, with the torch thread count stated. Each row carries the 1-minute load average:
on a shared machine other processes' load inflates the times (and makes 2 threads slower
than 1 when both cores are busy, because OpenMP waits at every barrier).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator

import numpy as np

from . import BenchOptions, BenchRow, load_note, median_seconds
from .model_hosts import host_rows

TITLE = 'single-view CNN inference (depth_fusion_ros.singleview)'

#: A reduced Eigen network for --quick smoke runs (the real one is 218 M parameters).
QUICK_EIGEN = {'vgg_widths': [8, 16, 16, 32, 32], 'fc_dim': 64}


@contextlib.contextmanager
def _torch_threads(n: int) -> Iterator[None]:
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _compact_predictor(device: str):
    """The shipped model when present (else an untrained compact net: same speed)."""
    from ..singleview.architectures import build_model
    from ..singleview.metadata import ModelMetadata
    from ..singleview.predictor import default_model_path, load_predictor, predictor_from_network

    if default_model_path().is_file():
        return load_predictor('default', device), f'shipped {default_model_path().name}'
    return predictor_from_network(
        build_model('compact'), ModelMetadata(), device
    ), 'untrained (no shipped model)'


def _eigen_predictor(device: str, quick: bool):
    from ..singleview.architectures import build_model
    from ..singleview.metadata import ModelMetadata
    from ..singleview.predictor import predictor_from_network

    net = build_model('eigen', QUICK_EIGEN if quick else None)
    meta = ModelMetadata(input_width=net.cfg.input_width, input_height=net.cfg.input_height)
    return predictor_from_network(net, meta, device), net


def _eigen_rows(
    opts: BenchOptions, rgb: np.ndarray, repeats: int, thread_counts: tuple[int, ...]
) -> list[BenchRow]:
    from ..singleview.architectures import count_parameters

    eigen, net = _eigen_predictor(opts.device, opts.quick)
    size = f'{net.cfg.input_width}x{net.cfg.input_height}'
    note = 'reduced widths (--quick)' if opts.quick else 'paper configuration'
    rows = [BenchRow('eigen: parameters', count_parameters(net), '', note)]
    for threads in thread_counts:
        with _torch_threads(threads):
            sec = median_seconds(lambda: eigen.predict(rgb), repeats, warmup=1)
            rows.append(BenchRow(f'eigen 320x240 (net {size}) predict ({threads} threads)', sec, 's',
                                 load_note(f'{1 / sec:.2f} Hz on {opts.device}')))  # fmt: skip
    return rows


def run(opts: BenchOptions) -> list[BenchRow]:
    import torch

    from ..singleview.architectures import count_parameters
    from ..singleview.predictor import default_model_path
    from ..singleview.simulated import simulate_prior

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    repeats = 3 if opts.quick else opts.repeats
    on_cpu = torch.device(opts.device).type == 'cpu'
    thread_counts = (2, 1) if on_cpu else (torch.get_num_threads(),)
    rows: list[BenchRow] = []

    compact, source = _compact_predictor(opts.device)
    rows.append(BenchRow('compact: parameters', count_parameters(compact.module), '', source))
    if default_model_path().is_file():
        rows.append(
            BenchRow('compact: shipped checkpoint size', default_model_path().stat().st_size / 1e6, 'MB')
        )
    for threads in thread_counts:
        with _torch_threads(threads):
            sec = median_seconds(lambda: compact.predict(rgb), repeats * 4, warmup=2)
            rows.append(BenchRow(f'compact 320x240 predict ({threads} threads)', 1 / sec, 'Hz',
                                 load_note(f'{sec * 1e3:.1f} ms on {opts.device}')))  # fmt: skip
    with _torch_threads(thread_counts[0]):
        batch = [rgb] * 4
        sec = median_seconds(lambda: compact.predict_batch(batch), repeats, warmup=2)
        rows.append(BenchRow(f'compact 320x240 batch of 4 ({thread_counts[0]} threads)', 4 / sec, 'img/s',
                             load_note()))  # fmt: skip

    rows += host_rows(
        opts,
        rgb,
        repeats,
        thread_counts,
        _torch_threads,
        functools.partial(median_seconds, warmup=2),
        load_note,
    )
    rows += _eigen_rows(opts, rgb, repeats, thread_counts)  # the 870 MB network is freed on return

    gt = 1.0 + 3.0 * rng.random((240, 320)).astype(np.float32)
    sec = median_seconds(lambda: simulate_prior(gt, rgb, seed=0), repeats, warmup=2)
    rows.append(BenchRow('simulated prior 320x240', sec * 1e3, 'ms', load_note('numpy, single thread')))
    return rows
