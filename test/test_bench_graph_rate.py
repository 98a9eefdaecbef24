"""The node-graph benchmark's sustained rate and its bag length: figures a user reads as the
graph's throughput, so a wrong one would be silently wrong."""

from __future__ import annotations

import pytest

from depth_fusion_ros.bench.node_graph import FRAMES, FRAMES_ENV, bench_frames, second_half_rate
from depth_fusion_ros.nodes.recorder import StampLog


def _log(arrivals: list[float]) -> dict[str, StampLog]:
    log = StampLog()
    for i, t in enumerate(arrivals):
        log.add(1000 + i, t)
    return {'fused': log}


def test_second_half_rate_reads_the_keyframes_after_the_middle_one() -> None:
    # A slow start (1 s between the first keyframes), then 10 a second: the run's own rate
    # mixes the two, the second half is the graph as it runs on.
    arrivals = [0.0, 1.0, 2.0, 3.0] + [3.0 + 0.1 * k for k in range(1, 9)]
    rate, count, span = second_half_rate(_log(arrivals), 'fused')
    assert count == len(arrivals) - 1 - len(arrivals) // 2
    assert span == pytest.approx(arrivals[-1] - arrivals[len(arrivals) // 2])
    assert rate == pytest.approx(10.0)


def test_second_half_rate_needs_arrivals() -> None:
    assert second_half_rate(_log([0.0, 0.1, 0.2, 0.3]), 'fused') is None
    assert second_half_rate(_log([0.0] * 3), 'other') is None


def test_bench_frames_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(FRAMES_ENV, raising=False)
    assert bench_frames(quick=False) == FRAMES
    assert bench_frames(quick=True) == 30
    monkeypatch.setenv(FRAMES_ENV, '500')
    assert bench_frames(quick=False) == 500
    for bad in ('many', '1', '-5'):
        monkeypatch.setenv(FRAMES_ENV, bad)
        with pytest.raises(ValueError, match=FRAMES_ENV):
            bench_frames(quick=False)
