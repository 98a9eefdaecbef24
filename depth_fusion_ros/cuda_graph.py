"""Replay launch-bound GPU work from CUDA graphs captured once per shape.

Why: on a GPU the package's stages are bound by launching kernels from Python, not by
arithmetic (docs/performance.md, "GPU": the sweep is ~900 op calls for a few milliseconds of
GPU work, the TV iterations ~800). A CUDA graph records such a sequence once and launches all
of it at once. It needs a function whose shapes depend only on its inputs' shapes, that makes
no host copy or synchronisation (no ``.item()``, ``nonzero``, ``torch.tensor`` from host data).
Callers make their work so (``multiview/tv_graph.py``, ``multiview/semidense_graph.py``).

:class:`GraphCache` keeps one capture per key (the caller's shapes and settings), with static
input buffers that each call copies into before replaying, and its own memory pool, for the
process's life. A capture that fails is logged once and that key returns None from then on,
so the caller runs its eager code.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable
from dataclasses import dataclass

import torch

log = logging.getLogger(__name__)

#: Runs on a side stream before capturing: compiled kernels compile, library handles are made.
WARMUP_RUNS = 2

Outputs = tuple[torch.Tensor, ...]


@dataclass
class _Captured:
    graph: torch.cuda.CUDAGraph
    inputs: tuple[torch.Tensor, ...]
    outputs: Outputs


def _as_tuple(out: torch.Tensor | Outputs) -> Outputs:
    return (out,) if isinstance(out, torch.Tensor) else tuple(out)


def capture(fn: Callable[..., torch.Tensor | Outputs], inputs: tuple[torch.Tensor, ...]) -> _Captured:
    """Warm ``fn`` up on a side stream, then record it over static copies of ``inputs``."""
    device = inputs[0].device
    # The inputs' device made current: the capture records on a stream of the current device.
    with torch.cuda.device(device):
        static = tuple(t.clone() for t in inputs)
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(WARMUP_RUNS):
                fn(*static)
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        # thread_local: another thread's CUDA calls (the graph's other nodes) must not break the capture.
        with torch.cuda.graph(graph, capture_error_mode='thread_local'):
            outputs = _as_tuple(fn(*static))
    return _Captured(graph, static, outputs)


class GraphCache:
    """Captured graphs of one stage, by key; :meth:`run` replays (capturing on first use)."""

    def __init__(self, stage: str) -> None:
        self.stage = stage
        self._graphs: dict[Hashable, _Captured | None] = {}
        self._lock = threading.Lock()  # one replay at a time: the static buffers are shared

    def __len__(self) -> int:
        """Graphs captured (failed captures not counted)."""
        return sum(1 for c in self._graphs.values() if c is not None)

    def run(
        self, key: Hashable, fn: Callable[..., torch.Tensor | Outputs], inputs: tuple[torch.Tensor, ...]
    ) -> Outputs | None:
        """``fn(*inputs)`` replayed from the graph of ``key`` (copies of its outputs), or None
        when capturing it failed: the caller then runs its eager code."""
        with self._lock:
            if key not in self._graphs:
                self._graphs[key] = self._capture(key, fn, inputs)
            captured = self._graphs[key]
            if captured is None:
                return None
            for buffer, value in zip(captured.inputs, inputs, strict=True):
                buffer.copy_(value)
            with torch.cuda.device(captured.inputs[0].device):
                captured.graph.replay()
            return tuple(t.clone() for t in captured.outputs)

    def _capture(
        self, key: Hashable, fn: Callable[..., torch.Tensor | Outputs], inputs: tuple[torch.Tensor, ...]
    ) -> _Captured | None:
        try:
            captured = capture(fn, inputs)
        except Exception as exc:  # capturing raises many types (CUDA, compiler); any failure means eager
            log.warning('%s: capturing a CUDA graph failed (%s); running eagerly', self.stage, exc)
            return None
        log.info('%s: captured a CUDA graph for %s', self.stage, key)
        return captured
