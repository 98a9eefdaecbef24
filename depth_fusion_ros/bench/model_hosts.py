"""ONNX Runtime vs torch (eager, ``torch.export``) on the shipped network, inside the
``single_view`` bench section (``depth-fusion bench --only single_view``).

The shipped compact network is exported to a temporary folder (``depth-fusion export``'s
code) and loaded by each host as a user's model would be. Figures are ``predict`` end to end
(resize, normalise, network, resize back) in Hz, the median of ``repeats`` runs after a
warm-up, with the same thread count for torch and ONNX Runtime (ORT's intra-op pool is sized
from torch's at load time).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from . import BenchOptions, BenchRow


def host_rows(
    opts: BenchOptions,
    rgb: np.ndarray,
    repeats: int,
    thread_counts: tuple[int, ...],
    torch_threads: Callable[[int], AbstractContextManager],
    median_seconds: Callable[..., float],
    note: Callable[[str], str],
) -> list[BenchRow]:
    """Rows per host and thread count: eager torch (the checkpoint), torch.export (.pt2),
    ONNX Runtime (each loaded under the thread count, so ORT's pool matches torch's)."""
    from ..singleview.export import export_network
    from ..singleview.predictor import default_model_path, load_predictor

    if not default_model_path().is_file():
        return [BenchRow('hosts: skipped', 0, '', 'the shipped model is missing')]
    rows: list[BenchRow] = []
    labels = {'eager': 'eager torch', 'pt2': 'torch.export .pt2', 'onnx': 'ONNX Runtime .onnx'}
    with tempfile.TemporaryDirectory(prefix='depth_fusion_bench_') as tmp:
        specs = {'eager': 'default'}
        for fmt in ('pt2', 'onnx'):
            try:
                specs[fmt] = str(export_network(Path(tmp) / f'compact.{fmt}', fmt)[0])
            except Exception as exc:  # a missing exporter dependency: say so, keep the other rows
                rows.append(BenchRow(f'hosts: {fmt} export failed', 0, '', f'{type(exc).__name__}: {exc}'))
        for threads in thread_counts:
            with torch_threads(threads):
                for host, spec in specs.items():
                    predictor = load_predictor(spec, opts.device)
                    providers = getattr(predictor.module, 'providers', None)
                    where = ','.join(p.replace('ExecutionProvider', '') for p in providers or [opts.device])
                    sec = median_seconds(lambda p=predictor: p.predict(rgb), repeats * 4)
                    rows.append(
                        BenchRow(
                            f'shipped predict, {labels[host]} ({threads} threads)',
                            1 / sec,
                            'Hz',
                            note(f'{sec * 1e3:.1f} ms on {where}'),
                        )
                    )
    return rows
