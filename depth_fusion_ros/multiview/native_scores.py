"""The sweep's coarse scores on a CPU in one native pass a row (``sweep_scores.c``).

After the cost volume of a chunk of keyframe pixels (``cost_volume.sample_cost``), the sweep
finds each row's best sample and its second-best ratio (``semidense._coarse_scores_torch``):
some thirty whole-volume torch passes, the minimum with its indices the slowest of them on a
CPU, and after the native cost the largest share of a sweep's torch time (about 10 of 57 ms a
keyframe of the bench's room on one thread). The kernel reads each row once and gives the same
numbers. On CUDA, or where it cannot be built (``native_build.load_native``), the function
returns ``None`` and the torch code runs.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import torch

from ..native_build import kernel_threads, load_native

#: Rows below which one call does not go to the threads (the hand-over costs more).
THREAD_MIN_ROWS = 2048


def native_coarse_scores(
    cost: torch.Tensor, count: torch.Tensor, need: float, exclusion: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """``(c1, best, distinct)`` per row of the cost volume ``cost`` (M, S), a sample's cost
    counting only where ``count`` (M, S) is at least ``need`` (``semidense._search_chunk``), or
    ``None`` where the kernel does not apply (not CPU float32 of one shape, or not here)."""
    applies = (
        cost.device.type == 'cpu'
        and cost.dtype == torch.float32
        and count.dtype == torch.float32
        and cost.dim() == 2
        and count.shape == cost.shape
        and cost.shape[1] > 0
    )
    lib = _library() if applies else None
    if lib is None:
        return None
    cost, count = cost.contiguous(), count.contiguous()
    rows, samples = cost.shape
    c1, distinct = torch.empty(rows, dtype=torch.float32), torch.empty(rows, dtype=torch.float32)
    best = torch.empty(rows, dtype=torch.int64)
    threads = kernel_threads(rows, THREAD_MIN_ROWS)
    lib.sweep_scores(
        cost.data_ptr(), count.data_ptr(), rows, samples, float(need), int(exclusion),
        c1.data_ptr(), best.data_ptr(), distinct.data_ptr(), threads,
    )  # fmt: skip
    return c1, best, distinct


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now; whether it will be used."""
    return _library() is not None


def _library() -> ctypes.CDLL | None:
    p, i64, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    signature = {'sweep_scores': [p, p, i64, i, f, i, p, p, p, i]}
    return load_native(Path(__file__).with_name('sweep_scores.c'), signature)
