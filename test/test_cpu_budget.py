"""The node graph's CPU budget (``cpu_budget.py``: the bench's rows and ``depth-fusion run``'s line):
which process the cores go to per fused keyframe. A wrong figure would point a user (or us) at
the wrong process, so it is checked against known work."""

from __future__ import annotations

import math
import os
import sys
import time
from types import SimpleNamespace

import pytest

from depth_fusion_ros.bench.node_graph import cpu_rows, descendants, second_half
from depth_fusion_ros.cpu_budget import CpuSampler, budget_line, cpu_seconds

linux = pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc (Linux)')


@linux
def test_cpu_seconds_counts_this_process_work_and_nothing_for_a_missing_one() -> None:
    before = cpu_seconds()
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    after = cpu_seconds()
    assert after - before == pytest.approx(0.3, abs=0.05)  # 10 ms ticks
    assert math.isnan(cpu_seconds(2**22 + 12345))  # above any pid_max: no such process


def _sampler(samples: list[tuple[float, dict[str, float]]]) -> CpuSampler:
    cpu = CpuSampler(processes=True, children=lambda pid: [])
    cpu.samples = samples
    return cpu


def test_the_window_reads_each_process_between_the_samples_around_its_ends() -> None:
    cpu = _sampler(
        [
            (0.0, {'fusion': 1.0, 'multi_view': 2.0}),
            (1.0, {'fusion': 1.5, 'multi_view': 3.0, 'late': 0.0}),
            (2.0, {'fusion': 2.5, 'multi_view': 3.2, 'late': 0.4}),
        ]
    )
    used = cpu.window(0.5, 1.5)
    assert used['fusion'] == pytest.approx(2.0 - 1.25)  # 1.25 at 0.5 s, 2.0 at 1.5 s
    assert used['multi_view'] == pytest.approx(3.1 - 2.5)
    assert 'late' not in used  # not read at the window's start: no figure rather than a wrong one
    assert cpu.window(0.5, 2.5) == {}  # past the last sample


def test_cpu_rows_give_milliseconds_per_keyframe_and_the_cores_used() -> None:
    # 10 keyframes after the middle one over 2 s; fusion used 1 s, multi_view 0.6 s.
    cpu = _sampler([(0.0, {'fusion': 0.0, 'multi_view': 0.0}), (4.0, {'fusion': 2.0, 'multi_view': 1.2})])
    fused = [0.0] * 11 + [2.0 + 0.2 * k for k in range(11)]  # middle at 2.0, last at 4.0
    rows = {r.name: r for r in cpu_rows('processes paced', cpu, second_half(fused))}
    assert rows['processes paced: CPU per fused keyframe, fusion'].value == pytest.approx(100.0)
    assert rows['processes paced: CPU per fused keyframe, multi_view'].value == pytest.approx(60.0)
    total = rows['processes paced: CPU of the second half, all processes']
    assert total.value == pytest.approx(0.8) and total.unit == 'cores'
    assert '160 ms per fused keyframe over 10 keyframes' in total.note
    assert cpu_rows('processes paced', cpu, second_half(fused[:4])) == []  # too few keyframes: no budget


@linux
def test_a_child_process_is_read_apart_from_its_parent() -> None:
    """The adaptation's training process (a child of the single-view node) is its own line: it
    runs niced on what the nodes leave, so it must not be charged to the node."""
    child = os.fork()
    if child == 0:  # pragma: no cover - the child burns CPU until killed
        while True:
            pass
    try:
        cpu = CpuSampler(processes=True, children=descendants)
        run = SimpleNamespace(processes={'single_view_node': SimpleNamespace(pid=os.getpid())})
        cpu(run)
        time.sleep(0.5)
        cpu(run)
        times = [t for t, _ in cpu.samples]
        used = cpu.window(times[0], times[-1])
        assert used["single_view's child processes"] >= 0.2  # the busy child
        assert used['single_view'] < used["single_view's child processes"]  # this process slept
    finally:
        os.kill(child, 9)
        os.waitpid(child, 0)


def test_each_process_tree_is_walked_again_only_every_refresh_period(monkeypatch: pytest.MonkeyPatch) -> None:
    """Walking every thread's children file at every progress call was the largest part of the
    runner's own CPU flat out (py-spy); the descendants found are read at each sample, and a
    child born later is found at the next walk with all its CPU."""
    import depth_fusion_ros.cpu_budget as cpu_budget

    walks: list[int | str] = []
    kids = {'now': [10]}

    def children(pid: int | str) -> list[int]:
        walks.append(pid)
        return list(kids['now'])

    clock = {'t': 100.0}
    monkeypatch.setattr(cpu_budget.time, 'monotonic', lambda: clock['t'])
    monkeypatch.setattr(cpu_budget, 'cpu_seconds', lambda pid='self': {10: 1.0, 11: 2.0}.get(pid, 0.5))
    cpu = CpuSampler(processes=True, children=children)
    run = SimpleNamespace(processes={'single_view_node': SimpleNamespace(pid=7)})
    for step in range(4):  # 0, 1.5, 3, 4.5 s: one walk
        clock['t'] = 100.0 + 1.5 * step
        cpu(run)
        kids['now'] = [10, 11]  # a second child is born after the first walk
    assert walks == [7]
    assert [v["single_view's child processes"] for _, v in cpu.samples] == [1.0] * 4
    clock['t'] = 100.0 + cpu_budget.TREE_REFRESH_S
    cpu(run)  # the period is over: walked again, the new child read with everything it used
    assert walks == [7, 7]
    assert cpu.samples[-1][1]["single_view's child processes"] == 3.0


def test_the_run_summary_line_divides_the_whole_playback_by_the_keyframes_fused() -> None:
    """``depth-fusion run`` prints this after its summary: no line rather than a wrong one."""
    cpu = _sampler([(10.0, {'fusion': 1.0, 'runner': 0.5}), (14.0, {'fusion': 2.6, 'runner': 0.9})])
    line = budget_line(cpu, fused=20, cores=2)
    want = 'CPU a fused keyframe over the 4 s of playback: fusion 80 ms, runner 20 ms; 0.50 of 2 cores'
    assert line == want
    assert budget_line(cpu, fused=0) is None  # nothing fused: nothing to divide by
    assert budget_line(_sampler(cpu.samples[:1]), fused=20) is None  # one sample is no span
    assert budget_line(_sampler([(0.0, {}), (4.0, {})]), fused=20) is None  # /proc gave nothing


def test_the_run_line_names_the_training_process_as_idle() -> None:
    """The training process often uses more CPU than a node (it takes what the nodes leave):
    the line says it runs at idle priority, so nobody reads it as the graph's limit."""
    child = "single_view's child processes"
    cpu = _sampler([(0.0, {'multi_view': 0.0, child: 0.0}), (2.0, {'multi_view': 0.6, child: 1.0})])
    line = budget_line(cpu, fused=10, cores=2)
    assert f'{child} (the training, at idle priority) 100 ms, multi_view 60 ms; 0.80 of 2 cores' in line


def test_only_the_single_view_nodes_children_are_called_the_training() -> None:
    """A kernel builder below the fusion node is not the training: no label it does not earn."""
    child = "fusion's child processes"
    cpu = _sampler([(0.0, {child: 0.0}), (2.0, {child: 0.5})])
    assert budget_line(cpu, fused=10, cores=2).endswith(f'{child} 50 ms; 0.25 of 2 cores')


def test_the_multi_view_nodes_child_is_called_the_calibration_checks() -> None:
    """The checks' process (``calibration_checks.process``) is the multi-view node's child: the
    line names it so, and the composed graph's children as both the training and the checks."""
    mv, graph = "multi_view's child processes", "graph's child processes"
    cpu = _sampler([(0.0, {mv: 0.0, graph: 0.0}), (2.0, {mv: 0.4, graph: 0.2})])
    line = budget_line(cpu, fused=10, cores=2)
    assert f'{mv} (the calibration checks) 40 ms' in line
    assert f'{graph} (the training, at idle priority; the calibration checks) 20 ms' in line
