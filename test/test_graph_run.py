"""``depth-fusion run`` end to end over real DDS: composed, as processes, and stopped by Ctrl-C.

A synthetic sequence (exact depth and poses) is converted to a rosbag2 and played through the
whole graph. An independent subscriber in this process (its own rclpy context) checks the
fused depth of every keyframe (32FC1, source header); the recorded bag is read back and its
fused depth scored against ground truth, which must match the offline ``evaluate`` result of
the same keyframes (online neighbours, same single-view network) within 5 %.

Kept affordable on a loaded 2-core machine: 320x240, 24 frames, a keyframe every 3rd frame,
replayed at half speed with work queues long enough that no keyframe is dropped, and a tiny
TorchScript network instead of the shipped one.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')
torch = pytest.importorskip('torch')

from conftest import save_torchscript_depth_model  # noqa: E402

from depth_fusion_ros.nodes.graph import (  # noqa: E402
    TOPIC_FUSED_DEPTH,
    TOPIC_IMAGE,
    RunOptions,
    orphan_segments,
    run_graph,
)

KEYFRAME_EVERY = 3
RATE = 0.5
FRAME_ID = 'camera_rgb_optical_frame'


class _ToyDepth(torch.nn.Module):
    """A stand-in single-view network: smooth, image-dependent, metric (2-2.5 m)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 + 0.5 * torch.sigmoid(x.mean(dim=1, keepdim=True))


@pytest.fixture(scope='module')
def toy_model(tmp_path_factory) -> Path:
    return save_torchscript_depth_model(_ToyDepth(), tmp_path_factory.mktemp('toy_model'), 'toy')


@pytest.fixture(scope='module')
def graph_bag(synthetic_tum_dir, tmp_path_factory) -> Path:
    from depth_fusion_ros.data.rosbag_convert import tum_to_rosbag

    return tum_to_rosbag(
        synthetic_tum_dir, tmp_path_factory.mktemp('graph') / 'synth', show_progress=False
    ).path


@pytest.fixture(scope='module')
def params_file(tmp_path_factory, toy_model) -> Path:
    """The graph's parameters as a user would write them (also exercises --params)."""
    path = tmp_path_factory.mktemp('params') / 'graph.yaml'
    path.write_text(
        f"""\
/**:
  ros__parameters:
    queue_size: 16
    qos_depth: 100
    stats_period: 0.0
multi_view_node:
  ros__parameters:
    keyframe_every: {KEYFRAME_EVERY}
single_view_node:
  ros__parameters:
    model: '{toy_model}'
fusion_node:
  ros__parameters:
    publish_points: false
    pair_timeout: 300.0
bag_replayer:
  ros__parameters:
    rate: {RATE}
"""
    )
    return path


@pytest.fixture(scope='module')
def expected_keyframes(graph_bag) -> list[int]:
    """Image stamps the multi-view node must make keyframes of: every k-th frame but the first
    (which has no past neighbour)."""
    stamps = list(_image_stamps(graph_bag))
    return [stamps[i] for i in keyframe_indices(graph_bag)]


def keyframe_indices(graph_bag: Path) -> list[int]:
    images = sum(1 for _ in _image_stamps(graph_bag))
    return [i for i in range(images) if i % KEYFRAME_EVERY == 0 and i > 0]


def _image_stamps(bag: Path):
    from depth_fusion_ros.data.rosbag_read import iter_messages

    for _, _, msg in iter_messages(bag, [TOPIC_IMAGE]):
        yield msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def evaluate_keyframes(sequence_dir: Path, method: str, keyframes: list[int], **options) -> dict[int, float]:
    """Per-keyframe MAE (m) of one ``depth-fusion evaluate`` method on ``keyframes``."""
    from depth_fusion_ros.data.tum import load_tum_sequence
    from depth_fusion_ros.evaluation.context import EvalOptions
    from depth_fusion_ros.evaluation.harness import evaluate_sequence

    seq = load_tum_sequence(sequence_dir)
    result = evaluate_sequence(
        seq, [method], EvalOptions(frames=None, keyframes=keyframes, **options), show_progress=False
    )
    maes = result.records[method].all.mae_per_frame
    return dict(zip(result.keyframes, maes, strict=True))


@pytest.fixture(scope='module')
def offline_mae(synthetic_tum_dir, graph_bag, toy_model) -> dict[int, float]:
    """``evaluate``'s fused method on the graph's keyframes: online neighbours, the same
    network, the node's fast fusion mode (no kernel compilation: a handful of frames)."""
    return evaluate_keyframes(
        synthetic_tum_dir,
        'fused',
        keyframe_indices(graph_bag),
        neighbour_mode='online',
        num_neighbours=4,
        single_view=str(toy_model),
        params={'fusion': {'mode': 'fast', 'compile_kernel': False}},
    )


class FusedListener:
    """An independent subscriber (own context and executor) to the fused depth."""

    def __init__(self) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import Image

        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('independent_listener', context=self.context)
        self.received: list = []
        self.node.create_subscription(Image, TOPIC_FUSED_DEPTH, self.received.append, 50)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # shut down under us
            return

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()
        self.thread.join(5.0)


def check_fused_messages(received: list, expected: list[int]) -> None:
    from depth_fusion_ros.data.messages import image_to_depth

    by_stamp = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m for m in received}
    got = [s for s in expected if s in by_stamp]
    assert len(got) >= 0.9 * len(expected), f'fused depth for {len(got)} of {len(expected)} keyframes'
    for stamp in got:
        msg = by_stamp[stamp]
        assert msg.encoding == '32FC1' and msg.header.frame_id == FRAME_ID
        depth = image_to_depth(msg)
        assert depth.shape == (240, 320) and np.isfinite(depth).mean() > 0.5


def check_accuracy_matches_offline(
    recorded: Path, sequence_dir: Path, keyframes: list[int], offline: dict[int, float]
) -> None:
    """The recorded fused depth, scored by ``evaluate``'s ``graph_fused``, within 5 % of offline."""
    online = evaluate_keyframes(
        sequence_dir, 'graph_fused', keyframes, params={'recorded': {'bag': str(recorded)}}
    )
    both = [i for i in keyframes if np.isfinite(online[i]) and np.isfinite(offline[i])]
    assert len(both) >= 0.9 * len(keyframes), f'{len(both)} of {len(keyframes)} keyframes scored'
    on = float(np.mean([online[i] for i in both]))
    off = float(np.mean([offline[i] for i in both]))
    print(f'fused MAE over {len(both)} keyframes: graph {on:.4f} m, offline evaluate {off:.4f} m')
    assert abs(on - off) <= 0.05 * off, f'online MAE {on:.4f} m vs offline {off:.4f} m'


def running(pid: int) -> bool:
    """Whether ``pid`` exists and is not a zombie."""
    try:
        return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0] != 'Z'
    except (OSError, IndexError):
        return False


def print_logs_of_failed_nodes(exit_codes: dict[str, int | None], log_dir: Path) -> None:
    """The end of each failed node's log, in the test's output: a node killed on CI for not
    stopping left its threads' stacks there (nodes/console.run_node), and CI keeps no files."""
    for name, code in exit_codes.items():
        log_file = log_dir / f'{name}.log'
        if code != 0 and log_file.is_file():
            print(f'--- {name} exited {code}; the end of {log_file}:')
            print('\n'.join(log_file.read_text(errors='replace').splitlines()[-120:]))


@pytest.mark.parametrize('processes', [False, True], ids=['composed', 'processes'])
def test_graph_fuses_every_keyframe_like_offline(
    processes, synthetic_tum_dir, graph_bag, params_file, expected_keyframes, offline_mae, tmp_path
):
    since = time.time()
    listener = FusedListener()
    try:
        out = tmp_path / 'out'
        result = run_graph(
            RunOptions(
                bag=graph_bag,
                params_file=params_file,
                record=out,
                processes=processes,
                log_dir=tmp_path / 'logs' if processes else None,
                flush_timeout=240.0,
                idle_timeout=120.0,
                # The independent listener is on the suite's domain: join it on purpose (a run
                # otherwise takes a private one, test_run_isolation.py).
                domain_id=int(os.environ['ROS_DOMAIN_ID']),
            )
        )
        time.sleep(0.2)
    finally:
        listener.close()
    assert result.complete, result.missing
    assert result.recorded == out and out.is_dir() and not (tmp_path / 'out.partial').exists()
    assert set(result.announced) <= set(expected_keyframes)
    check_fused_messages(listener.received, expected_keyframes)
    check_accuracy_matches_offline(out, synthetic_tum_dir, keyframe_indices(graph_bag), offline_mae)
    if processes:
        print_logs_of_failed_nodes(result.exit_codes, tmp_path / 'logs')
        assert result.exit_codes == {
            'single_view_node': 0,
            'multi_view_node': 0,
            'fusion_node': 0,
            'bag_replayer': 0,
        }
        assert no_orphans_since(since), 'Fast DDS shared memory left behind'


def no_orphans_since(since: float, timeout: float = 15.0) -> bool:
    """No shared-memory segment created since ``since`` is left unmapped, within ``timeout`` s:
    the tests on the other pytest workers that kill a node on purpose leave theirs for the
    moment until they (or their run) remove them; a segment this run left stays."""
    deadline = time.monotonic() + timeout
    while orphan_segments(since):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.5)
    return True


@pytest.mark.parametrize(
    ('processes', 'sig'),
    [(True, signal.SIGINT), (False, signal.SIGTERM)],
    ids=['processes-SIGINT', 'composed-SIGTERM'],
)
def test_ctrl_c_stops_processes_cleanly(graph_bag, params_file, tmp_path, processes, sig):
    """SIGINT to ``depth-fusion run --processes`` mid-bag: children gone, partial bag kept, exit
    130. Composed, SIGTERM does the same: its nodes spin events executors (node_executor.py),
    whose ``spin()`` once ignored it with a core at 100 %."""
    since = time.time()
    out = tmp_path / 'interrupted'
    cmd = [
        sys.executable,
        '-m',
        'depth_fusion_ros.cli.main',
        'run',
        '--bag',
        str(graph_bag),
        '--params',
        str(params_file),
        *(['--processes'] if processes else []),
        '--record',
        str(out),
        '--set',
        'bag_replayer.loop=true',
    ]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ.copy()
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not any('[bag_replayer]: playing' in ln for ln in lines):
        assert proc.poll() is None, ''.join(lines)
        time.sleep(0.2)
    time.sleep(3.0)  # mid-bag (it loops), nodes busy
    proc.send_signal(sig)
    code = proc.wait(60)
    reader.join(5)
    output = ''.join(lines)
    assert code == 130, output
    pids = [int(p) for p in re.findall(r'(?:started|forked) \w+ \(pid (\d+)\)', output)]
    assert len(pids) == (4 if processes else 0), output
    time.sleep(0.5)
    alive = [p for p in pids if running(p)]
    assert alive == [], f'children still running: {alive}'
    assert (tmp_path / 'interrupted.partial').is_dir() and not out.exists()
    assert no_orphans_since(since), orphan_segments(since)


def test_a_bad_fork_switch_is_one_line_before_anything_starts(graph_bag, monkeypatch):
    """``DEPTH_FUSION_FORK_NODES`` other than 0 or 1 stops ``run --processes`` with one line
    naming the variable, before a node, a recorder or the fork server exists."""
    from depth_fusion_ros.nodes.graph import GraphError, GraphRun, RunOptions

    monkeypatch.setenv('DEPTH_FUSION_FORK_NODES', 'maybe')
    run = GraphRun(RunOptions(bag=graph_bag, processes=True))
    with pytest.raises(GraphError, match=r"DEPTH_FUSION_FORK_NODES='maybe': expected 1") as caught:
        run.run()
    assert '\n' not in str(caught.value)
    assert run.processes == {} and run.recorder is None
