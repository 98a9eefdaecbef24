"""The training thread yields the CPU to the real-time path (``adaptation.nice``)."""

from __future__ import annotations

import os
import sys
import threading
from types import SimpleNamespace

import pytest

from depth_fusion_ros.adaptation.online import OnlineAdaptation, WeightSlot


class _RecordingAdapter:
    """Stands in for the Adapter's ``observe``: records the niceness its work runs at."""

    def __init__(self) -> None:
        self.seen: list[int] = []
        self.warmed: list[int] = []

    def warm_up(self):
        self.warmed.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    def observe(self, sample, abort, behind=False):
        self.seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        return SimpleNamespace(status='skipped')


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='per-thread niceness is Linux-only')
def test_training_runs_at_lower_priority_and_the_caller_does_not():
    adapter = _RecordingAdapter()
    own = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    online = OnlineAdaptation(adapter, WeightSlot(predictor=None), queue_size=2, nice=10)
    try:
        online.submit(object())
        assert online.wait_idle(10.0)
    finally:
        assert online.stop(10.0)
    assert adapter.seen == [min(19, own + 10)]
    assert adapter.warmed == [min(19, own + 10)]  # the optimiser's first-use cost, niced too
    assert online.thread_nice == min(19, own + 10)
    # the thread that submitted (inference's) kept its priority
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == own


def test_nice_out_of_range_is_an_error():
    with pytest.raises(ValueError, match='nice'):
        OnlineAdaptation(_RecordingAdapter(), WeightSlot(predictor=None), nice=25)
