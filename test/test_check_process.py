"""The calibration checks in a process of their own (``nodes/check_process.py``): the same
verdicts as on the node's threads, at a lower priority, and a process that dies is said once
while the check goes on on the runner's thread."""

from __future__ import annotations

import os
import signal
import time

import pytest

from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.multiview.focal_check import FocalCheckConfig
from depth_fusion_ros.multiview.time_offset_check import TimeOffsetCheckConfig
from depth_fusion_ros.nodes.check_process import CheckProcess
from depth_fusion_ros.nodes.focal_check_runner import FocalCheckRunner
from depth_fusion_ros.nodes.testing import RosHarness
from depth_fusion_ros.nodes.time_offset_check_runner import TimeOffsetCheckRunner

PAIRS = 12


@pytest.fixture(scope='module')
def wrong_focal():
    return render_sequence(stress_config('wrong_focal', width=320, height=240, frames=40, seed=5))


def _niceness(pid: int) -> int:
    """A process's niceness, from ``/proc`` (field 19 of its stat line)."""
    with open(f'/proc/{pid}/stat') as f:
        return int(f.read().rsplit(')', 1)[1].split()[16])


def _stream(runner, sequence, period: float = 0.0, frames=None) -> None:
    """Offer the frames as a stream, waiting after each until the runner caught up: the check
    then takes the same samples however loaded the machine."""
    for frame in sequence.frames if frames is None else frames:
        runner.offer(frame, sequence.camera)
        time.sleep(period)
        assert RosHarness.wait_for(lambda: not runner.pending, 30.0)


def _run_focal(sequence, host):
    reports = []
    runner = FocalCheckRunner(FocalCheckConfig(pairs=PAIRS), lambda cam, est: reports.append(est))
    runner.host = host
    _stream(runner, sequence)
    assert RosHarness.wait_for(lambda: bool(reports), 30.0), runner.status()
    runner.close()
    return runner, reports


def test_the_focal_check_in_its_process_says_what_a_thread_says(wrong_focal):
    host = CheckProcess(nice=10)
    try:
        remote, remote_reports = _run_focal(wrong_focal, host)
        assert host.pid is not None and _niceness(host.pid) == _niceness(os.getpid()) + 10
        assert host.lost is None
    finally:
        host.close()
    local, local_reports = _run_focal(wrong_focal, None)
    assert len(remote_reports) == 1 and len(local_reports) == 1
    a, b = remote_reports[0], local_reports[0]
    assert a.verdict == b.verdict == 'disagrees'
    assert a.fx == pytest.approx(b.fx, rel=1e-9) and a.pairs == b.pairs == PAIRS
    assert remote.status() == local.status() and remote.status().startswith('disagrees: fx 288.8 ->')
    assert remote.cpu > 0.0  # the process's CPU on the check, as it said it
    # The process is gone with its node's close.
    assert host._proc.poll() is not None


def test_the_time_offset_check_in_its_process_reads_every_pose_and_its_samples():
    late = render_sequence(
        stress_config('time_offset', width=240, height=180, frames=60, seed=5, pose_time_offset=0.02)
    )
    host = CheckProcess(nice=10)
    reports = []
    runner = TimeOffsetCheckRunner(TimeOffsetCheckConfig(), 0.0, lambda cam, est: reports.append(est))
    runner.host = host
    try:
        _stream(runner, late, period=0.01)
        assert RosHarness.wait_for(lambda: bool(reports), 30.0), runner.status()
    finally:
        runner.close()
        host.close()
    assert reports[0].verdict == 'disagrees', runner.status()
    assert runner.correction == pytest.approx(-0.02, abs=0.003)
    assert runner.status().startswith('disagrees: -20 +- ')


def test_a_check_process_that_dies_is_said_once_and_the_check_goes_on_here(wrong_focal):
    said = []
    host = CheckProcess(nice=10, on_lost=said.append)
    reports = []
    runner = FocalCheckRunner(FocalCheckConfig(pairs=PAIRS), lambda cam, est: reports.append(est))
    runner.host = host
    frames = wrong_focal.frames
    try:
        _stream(runner, wrong_focal, frames=frames[:10])
        assert runner.collected > 0 and host.pid is not None
        os.kill(host.pid, signal.SIGKILL)
        host._proc.wait(10)
        # The check starts over on the runner's thread from the next frame: the stream played
        # back and forth gives it its pairs again.
        _stream(runner, wrong_focal, frames=frames[10:] + frames[::-1] + frames)
        assert RosHarness.wait_for(lambda: bool(reports), 30.0), runner.status()
    finally:
        runner.close()
        host.close()
    assert len(said) == 1 and ('ended while checking' in said[0] or 'pipe closed' in said[0]), said
    assert reports[0].verdict == 'disagrees', runner.status()


def test_a_check_process_started_ahead_serves_its_first_item_and_ends_with_close(wrong_focal):
    """The node starts the process as it starts (its imports done before the stream); one that
    was never started starts with its first item; either ends with its node's close."""
    lazy = CheckProcess()
    assert lazy.pid is None
    lazy.close()
    assert lazy.pid is None
    host = CheckProcess()
    host.start()
    pid = host.pid
    assert pid is not None
    host.start()  # once
    assert host.pid == pid
    runner = FocalCheckRunner(FocalCheckConfig(pairs=PAIRS), lambda *_: None)
    runner.host = host
    try:
        _stream(runner, wrong_focal, frames=wrong_focal.frames[:5])
        assert runner.collected > 0 and host.pid == pid and host.lost is None
    finally:
        runner.close()
        host.close()
    assert host._proc.poll() is not None


def test_the_node_starts_its_checks_process_as_it_starts_and_ends_it_with_itself():
    """``multi_view_node``: the process is started with the node (its imports done before the
    stream), at ``calibration_checks.nice``; none when the checks are all off or
    ``calibration_checks.process`` is false."""
    from test_nodes_multi_view import _mv_node

    off = {f'{check}.mode': 'off' for check in ('focal_check', 'time_offset_check', 'mount_check')}
    with RosHarness() as ros:
        node = _mv_node(ros, **{'calibration_checks.nice': 7})
        host = node.check_process
        assert host is not None and host.pid is not None
        want = _niceness(os.getpid()) + 7  # the child lowers its own priority first thing
        assert RosHarness.wait_for(lambda: _niceness(host.pid) == want, 10.0)
        assert _mv_node(ros, **off).check_process is None
        assert _mv_node(ros, **{'calibration_checks.process': False}).check_process is None
    assert host._proc.wait(10) is not None  # the harness destroyed the node
