"""``depth-fusion launch``: the live graph started as one, its inputs remapped, stopped as one.

Real processes on this test run's own ROS domain (conftest): the remapped pose topic is checked
on the DDS graph, Ctrl-C must leave no node running, and a node that dies must stop the rest.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')

NODES = ('multi_view_node', 'single_view_node', 'fusion_node')


def running(pid: int) -> bool:
    try:
        return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0] != 'Z'
    except (OSError, IndexError):
        return False


def start(log_dir: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, '-m', 'depth_fusion_ros.cli.main', 'launch', '--log-dir', str(log_dir), *extra]
    env = os.environ.copy()
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


def wait_ready(proc: subprocess.Popen, log_dir: Path, nodes=NODES, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        logs = {n: log_dir / f'{n}.log' for n in nodes}
        if all(p.exists() and f'[{n}]: ready' in p.read_text() for n, p in logs.items()):
            return
        assert proc.poll() is None, proc.stdout.read()
        time.sleep(0.2)
    raise AssertionError(f'not ready after {timeout:g} s')


@contextlib.contextmanager
def launched(log_dir: Path, *extra: str) -> Iterator[subprocess.Popen]:
    """``depth-fusion launch`` running with every node ready; killed at the end if still up."""
    proc = start(log_dir, *extra)
    try:
        wait_ready(proc, log_dir)
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()


def subscribers(topic: str) -> set[str]:
    """The node names subscribed to ``topic`` on this test's domain, as DDS discovery sees them."""
    import rclpy

    context = rclpy.context.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node('launch_probe', context=context)
        deadline = time.monotonic() + 20.0
        names: set[str] = set()
        while time.monotonic() < deadline and 'multi_view_node' not in names:
            names = {info.node_name for info in node.get_subscriptions_info_by_topic(topic)}
            time.sleep(0.2)
        node.destroy_node()
        return names
    finally:
        rclpy.shutdown(context=context)


def publish_keyframe_events(events: list[tuple[int, str]]) -> None:
    """Publish keyframe events (``graph_events``) as the nodes would, once the launch's
    listener has matched."""
    import rclpy
    from std_msgs.msg import Header

    from depth_fusion_ros.nodes.graph_events import TOPIC_KEYFRAME_EVENTS, events_qos

    context = rclpy.context.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node('launch_events_probe', context=context)
        pub = node.create_publisher(Header, '/' + TOPIC_KEYFRAME_EVENTS, events_qos())
        deadline = time.monotonic() + 20.0
        while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert pub.get_subscription_count() >= 1, 'the launch does not listen to the keyframe events'
        for stamp, event in events:
            msg = Header(frame_id=event)
            msg.stamp.sec, msg.stamp.nanosec = divmod(stamp, 10**9)
            pub.publish(msg)
        time.sleep(1.0)  # reliable: delivered, then this participant leaves
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_launch_remaps_the_inputs_and_ctrl_c_stops_every_node(tmp_path: Path):
    args = ('--pose', '/launch_test/slam_pose', '--set', 'fusion_node.stats_period=0.0')
    with launched(tmp_path, *args) as proc:
        assert 'multi_view_node' in subscribers('/launch_test/slam_pose')
        # What the nodes say of four keyframes: the launch's closing count (as run's summary).
        kf = [10**9 * (100 + i) for i in range(4)]
        publish_keyframe_events(
            [(s, 'chosen') for s in kf]
            + [(kf[0], 'fused'), (kf[1], 'fused'), (kf[2], 'dropped:multi_view.worker_queue_full')]
        )
        proc.send_signal(signal.SIGINT)
        code = proc.wait(60)
    output = proc.stdout.read()
    assert code == 0, output
    assert re.search(
        r'4 keyframes chosen, 2 fused, 2 dropped \(in_flight_at_stop=1, multi_view.worker_queue_full=1\) '
        r'in [\d.]+ s \(live\)',
        output,
    ), output
    assert re.search(r'\(live\); no image reached multi_view_node \(check --image', output), output
    pids = [int(p) for p in re.findall(r'(?:forked|started) \w+ \(pid (\d+)', output)]
    assert len(pids) == 3, output
    assert '3 nodes stopped cleanly in' in output, output  # a clean stop says so
    time.sleep(0.5)
    assert [p for p in pids if running(p)] == []
    for node in NODES:
        assert 'final counters' in (tmp_path / f'{node}.log').read_text()


def test_a_launch_stopped_before_anything_was_fused_fails_and_says_why(tmp_path: Path):
    """No camera on the topic: the nodes stop cleanly, but nothing was fused, so not exit 0."""
    with launched(tmp_path, '--image', '/launch_test/no_camera') as proc:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(60)
    output = proc.stdout.read()
    assert code == 1, output
    assert '3 nodes stopped cleanly in' in output, output
    assert output.rstrip().endswith('nothing was fused: no image reached multi_view_node'), output


def test_a_node_that_dies_stops_the_others_and_the_launch_fails(tmp_path: Path):
    from depth_fusion_ros.nodes.graph.dds import participant_segments_of

    # The log of a run before, in the same --log-dir: a launch again after a crash keeps it.
    earlier = '[ERROR] [fusion_node]: the crash of the run before\n'
    (tmp_path / 'fusion_node.log').write_text(earlier)
    with launched(tmp_path) as proc:
        output_so_far = ''.join(proc.stdout.readline() for _ in range(3))
        pids = dict(re.findall(r'(?:forked|started) (\w+) \(pid (\d+)', output_so_far))
        assert set(pids) == set(NODES), output_so_far
        segments = participant_segments_of(int(pids['fusion_node']))
        assert segments, 'fusion_node maps no participant segment'
        os.kill(int(pids['fusion_node']), signal.SIGKILL)
        code = proc.wait(60)
    output = proc.stdout.read()
    assert code == 1, output
    assert 'fusion_node was killed by SIGKILL (exit -9): the other nodes were stopped' in output
    # Its shared memory, which no shutdown removed, is not left in /dev/shm.
    assert 'shared-memory segments left by killed nodes' in output, output
    assert not [s for s in segments if (Path('/dev/shm') / s).exists()]
    time.sleep(0.5)
    assert [n for n, p in pids.items() if running(int(p))] == []
    log = (tmp_path / 'fusion_node.log').read_text()
    assert log.startswith(earlier) and re.search(
        r'\n=== fusion_node started \S+ \S+ UTC by depth-fusion', log
    )
    assert '[fusion_node]: ready' in log.split('=== fusion_node started')[1]


@pytest.mark.parametrize(
    ('args', 'message'),
    [
        (['--set', 'bag_replayer.rate=2'], 'bag_replayer is not started (launch plays no bag)'),
        (['--set', 'map_node.map.voxel_size=0.05'], 'map_node is not started; add --map'),
        (['--set', 'fusion_node.no_such_parameter=1'], 'no_such_parameter'),
        (['--params', 'no/such/file.yaml'], '--params no/such/file.yaml: no such file'),
    ],
)
def test_bad_launch_options_are_one_line_before_any_node_starts(tmp_path: Path, args, message):
    proc = start(tmp_path / 'logs', *args)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert output.strip().splitlines() == [output.strip().splitlines()[0]]
    assert output.startswith('depth-fusion launch: error: ') and message in output
    assert not (tmp_path / 'logs').exists()
