"""Where the single-view node's keyframes spend their time in a composed graph, one line each:
the wait in the worker's queue, the network's ``predict`` (its read back to the host
included) and the rest (the message and its publish).

    python scripts/diag/sv_stall.py cuda

Why: on an H200 the composed real-time graph lost its first second of keyframes in the
single-view node's queue (docs/performance.md "GPU", 2026-11-30, "Cause 2"), which the CPU
does not. This wraps ``SingleViewNode._process`` and the predictor it calls, then runs
``bench --only node_graph`` (``DEPTH_FUSION_BENCH_GRAPH_RUNS`` defaults here to
``composed:realtime:1``: the nodes must share this process for the wrap to see them).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from typing import Any

from depth_fusion_ros.bench import BenchOptions, node_graph
from depth_fusion_ros.nodes import single_view_node

RECORDS: list[tuple[float, float, float, float, str]] = []  # received, start, predicted, end, thread
_LOCK = threading.Lock()
_ORIGINAL_PROCESS = single_view_node.SingleViewNode._process


class _TimedPredictor:
    """The node's predictor, noting when ``predict`` returned (the result is on the host)."""

    def __init__(self, inner: Any, marks: dict[str, float]) -> None:
        self._inner, self._marks = inner, marks

    def predict(self, rgb: Any) -> Any:
        out = self._inner.predict(rgb)
        self._marks['predicted'] = time.monotonic()
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def _timed_process(self: Any, job: Any) -> None:
    start = time.monotonic()
    marks: dict[str, float] = {}
    original = self.current_predictor
    self.current_predictor = lambda: _TimedPredictor(original(), marks)
    try:
        _ORIGINAL_PROCESS(self, job)
    finally:
        del self.current_predictor
        end = time.monotonic()
        thread = threading.current_thread().name
        with _LOCK:
            RECORDS.append((job.received_at, start, marks.get('predicted', end), end, thread))


def main() -> None:
    device = sys.argv[1] if len(sys.argv) > 1 else 'cpu'
    os.environ.setdefault(node_graph.RUNS_ENV, 'composed:realtime:1')
    single_view_node.SingleViewNode._process = _timed_process
    rows = node_graph.run(BenchOptions(device=device, repeats=1))
    for row in rows:
        if any(key in row.name for key in ('fused', 'dropped', 'in → out', 'latency image')):
            print(f'{row.name:70s} {row.value:10.4g} {row.unit} {row.note}')
    print('keyframe  arrived_s  wait_ms  predict_ms  publish_ms  thread')
    first = RECORDS[0][0] if RECORDS else 0.0
    for i, (received, start, predicted, end, thread) in enumerate(RECORDS):
        wait, predict, rest = (start - received) * 1e3, (predicted - start) * 1e3, (end - predicted) * 1e3
        print(f'{i:8d}  {received - first:9.3f}  {wait:7.1f}  {predict:10.1f}  {rest:10.1f}  {thread}')


if __name__ == '__main__':
    main()
