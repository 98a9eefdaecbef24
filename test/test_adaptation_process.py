"""Adaptation in a training process of its own (adaptation/remote_adapter.py, trainer_process.py):
the same update as in process, the weights back for inference, stop mid-update, a dead child."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time

import numpy as np
import pytest
import torch
from test_adaptation import _gt_sample

from depth_fusion_ros.adaptation.adapter import Adapter
from depth_fusion_ros.adaptation.config import AdaptConfig
from depth_fusion_ros.adaptation.online import OnlineAdaptation, WeightSlot
from depth_fusion_ros.adaptation.remote_adapter import RemoteAdapter
from depth_fusion_ros.singleview.predictor import load_predictor

pytestmark = pytest.mark.usefixtures('one_torch_thread')

CONFIG = {'steps_per_keyframe': 2, 'replay_per_step': 1, 'min_points': 5, 'guard_tolerance': 1e9}


@pytest.fixture()
def remote(tiny_model):
    adapter = RemoteAdapter(tiny_model, AdaptConfig(**CONFIG), nice=0)
    yield adapter
    adapter.close()


def _weights(net: torch.nn.Module) -> list[torch.Tensor]:
    return [t.detach().clone() for t in net.state_dict().values()]


def test_an_update_in_the_process_gives_the_in_process_weights(remote, tiny_model, small_sequence):
    local = Adapter.from_spec(tiny_model, AdaptConfig(**CONFIG))
    before = remote.predictor().predict(small_sequence.frames[2].rgb)
    for i in (0, 1):
        sample = _gt_sample(small_sequence, i, scale=1.3)
        want, got = local.observe(sample), remote.observe(sample)
        assert (got.status, got.version, got.steps) == (want.status, want.version, want.steps)
        assert (got.status, got.version, got.steps) == ('updated', i + 1, 2)
        assert got.loss_last == pytest.approx(want.loss_last, rel=1e-5)
    for a, b in zip(_weights(remote.net), _weights(local.net), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    assert remote.counters.updated == 2 and remote.counters.observed == 2
    after = remote.predictor().predict(small_sequence.frames[2].rgb)
    assert not np.array_equal(after, before)  # inference got the new weights
    np.testing.assert_allclose(after, local.predictor().predict(small_sequence.frames[2].rgb), rtol=1e-4)


def test_stop_mid_update_keeps_the_weights_and_reports_stopped(remote, small_sequence):
    before = _weights(remote.net)
    report = remote.observe(_gt_sample(small_sequence, 0, scale=1.3), abort=lambda: True)
    assert report.status == 'skipped' and report.reason == 'stopped', report
    assert remote.version == 0
    for a, b in zip(_weights(remote.net), before, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_an_abort_that_comes_after_its_update_does_not_stop_the_next(remote, small_sequence):
    from depth_fusion_ros.adaptation.trainer_process import send

    assert remote.observe(_gt_sample(small_sequence, 0, scale=1.3)).status == 'updated'
    send(remote._conn, ('abort',))  # a stop asked as the update ended: too late for it
    report = remote.observe(_gt_sample(small_sequence, 1, scale=1.3))
    assert (report.status, report.steps, remote.version) == ('updated', 2, 2), report


class _StepAdapter:
    """The adapter's side of the protocol for ``trainer_process._loop``: an update of up to
    2000 steps of 1 ms that looks at ``abort`` before each step, as ``Adapter.observe`` does."""

    def __init__(self) -> None:
        self.net = torch.nn.Linear(2, 1)
        self.counters = None
        self.version = 0

    def observe(self, sample, abort, behind=False):
        from depth_fusion_ros.adaptation.adapter import UpdateReport

        for step in range(2000):
            if abort():
                return UpdateReport(sample, 'skipped', 'stopped', steps=step, version=self.version)
            time.sleep(0.001)
        self.version += 1
        return UpdateReport(sample, 'updated', steps=2000, version=self.version)


def test_the_trainer_loop_stops_the_update_an_abort_follows_and_only_that_one():
    # In one process, with the loop on a thread: an abort sent right after its request, before
    # the loop has even read the request (what a loaded machine does to the child), still
    # stops that update; a late abort is skipped; a stop mid-update ends the loop after its report.
    from depth_fusion_ros.adaptation.trainer_process import _loop, receive, send

    parent, child = multiprocessing.Pipe()
    send(parent, ('observe', 0, False))
    send(parent, ('abort',))
    loop = threading.Thread(target=_loop, args=(child, _StepAdapter()), daemon=True)
    loop.start()
    report = receive(parent)[1]
    assert (report.status, report.reason, report.steps) == ('skipped', 'stopped', 0), report
    send(parent, ('abort',))  # late: for no update
    send(parent, ('observe', 1, False))
    kind, report, _, weights = receive(parent)
    assert (kind, report.status, report.version, len(weights)) == ('report', 'updated', 1, 2), report
    send(parent, ('observe', 2, False))
    time.sleep(0.05)
    send(parent, ('stop',))
    report = receive(parent)[1]
    assert report.status == 'skipped' and 0 < report.steps < 2000, report
    loop.join(10)
    assert not loop.is_alive()


def test_a_training_process_that_dies_ends_training_not_inference(remote, small_sequence, caplog):
    assert remote.observe(_gt_sample(small_sequence, 0, scale=1.3)).status == 'updated'
    weights = _weights(remote.net)
    os.kill(remote.pid, signal.SIGKILL)
    reports = [remote.observe(_gt_sample(small_sequence, i, scale=1.3)) for i in (1, 2)]
    assert [r.status for r in reports] == ['skipped', 'skipped']
    assert all(r.reason.startswith('trainer_stopped: the training process ended') for r in reports), reports
    assert remote.counters.reasons['trainer_stopped'] == 2
    assert sum('no more training in this run' in r.getMessage() for r in caplog.records) == 1  # said once
    for a, b in zip(_weights(remote.net), weights, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert np.isfinite(remote.predictor().predict(small_sequence.frames[0].rgb)).all()


def test_the_training_thread_swaps_in_the_process_weights(remote, tiny_model, small_sequence):
    slot = WeightSlot(load_predictor(tiny_model))
    online = OnlineAdaptation(remote, slot, queue_size=4)
    try:
        for i in (0, 1, 2):
            online.submit(_gt_sample(small_sequence, i, scale=1.3))
        assert online.wait_idle(120.0)
    finally:
        assert online.stop()
    assert slot.version == remote.version == 3 and online.failed == 0
    rgb = small_sequence.frames[3].rgb
    np.testing.assert_array_equal(slot.get()[0].predict(rgb), remote.predictor().predict(rgb))


def test_a_restart_in_the_process_gives_back_the_loaded_weights(remote, tiny_model, small_sequence):
    """The child starts over (Adapter.restart) and sends the loaded weights back for inference."""
    loaded = _weights(remote.net)
    rgb = small_sequence.frames[3].rgb
    for i in (0, 1):
        assert remote.observe(_gt_sample(small_sequence, i, scale=1.3)).status == 'updated'
    assert any(not torch.equal(a, b) for a, b in zip(_weights(remote.net), loaded, strict=True))
    report = remote.restart(2, 'turned')
    assert (report.status, report.version, remote.version) == ('restarted', 3, 3)
    assert remote.counters.restarts == 1
    for a, b in zip(_weights(remote.net), loaded, strict=True):
        assert torch.equal(a, b)
    np.testing.assert_array_equal(remote.predictor().predict(rgb), load_predictor(tiny_model).predict(rgb))
    assert remote.observe(_gt_sample(small_sequence, 2, scale=1.3)).status == 'updated'  # learns again


def test_a_model_that_cannot_adapt_is_a_start_up_error(tmp_path):
    with pytest.raises(FileNotFoundError, match='single-view model not found'):
        RemoteAdapter(str(tmp_path / 'missing.pt'))


def test_the_bench_counts_the_training_process_in_the_graphs_memory(remote):
    from depth_fusion_ros.bench.node_graph import descendants, rss_mb, tree_mb

    remote.warm_up()  # the child has imported torch and built its network
    assert remote.pid in descendants()
    assert tree_mb() >= rss_mb() + rss_mb(remote.pid) - 1.0  # this process and the child (MB)


def test_a_node_shutting_down_does_not_wait_for_a_training_process_still_starting(tiny_model, small_sequence):
    remote = RemoteAdapter(tiny_model, AdaptConfig(**CONFIG), nice=0)
    remote.cancel()  # at once: the child is still importing torch
    report = remote.observe(_gt_sample(small_sequence, 0, scale=1.3))
    assert (report.status, report.reason) == ('skipped', 'stopped')
    assert not remote.ready and remote.counters.reasons == {'stopped': 1}
    assert remote.close()  # ended at once: nothing in a child still starting is worth waiting for
    assert remote._proc.poll() is not None


def test_the_training_process_imports_the_package_the_node_runs():
    from pathlib import Path

    import depth_fusion_ros
    from depth_fusion_ros.child_process import child_environment

    first = child_environment()['PYTHONPATH'].split(os.pathsep)[0]
    assert first == str(Path(depth_fusion_ros.__file__).resolve().parents[1])


@pytest.mark.skipif(not hasattr(os, 'SCHED_IDLE'), reason='SCHED_IDLE is Linux only')
def test_an_idle_training_process_runs_under_sched_idle_and_a_plain_one_does_not(tiny_model, small_sequence):
    """``adaptation.idle_policy``: the child sets its own policy before it imports torch; the
    node's process keeps its own (only the trainer yields the cores)."""
    idle = RemoteAdapter(tiny_model, AdaptConfig(**CONFIG), nice=0, idle=True)
    plain = RemoteAdapter(tiny_model, AdaptConfig(**CONFIG), nice=0)
    try:
        idle.warm_up()
        plain.warm_up()
        assert os.sched_getscheduler(idle.pid) == os.SCHED_IDLE
        assert os.sched_getscheduler(plain.pid) == os.SCHED_OTHER
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
        report = idle.observe(_gt_sample(small_sequence, 0, scale=1.3))  # it still trains
        assert (report.status, report.version) == ('updated', 1), report
    finally:
        idle.close()
        plain.close()
