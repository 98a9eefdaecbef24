"""Fault injection: ``kill -9`` of each node of ``depth-fusion run --processes``.

The run must stop by itself with one error naming the node and how it died, print how many
keyframes were fused before, leave a readable partial recording, and leave no child running.
The bag loops so the kill always lands mid-run.
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

import pytest

pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')
torch = pytest.importorskip('torch')

from conftest import save_torchscript_depth_model  # noqa: E402
from run_bags import small_bag, write_params  # noqa: E402


class _ToyDepth(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 + 0.5 * torch.sigmoid(x.mean(dim=1, keepdim=True))


@pytest.fixture(scope='module')
def setup(synthetic_tum_dir, tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp('faults')
    model = save_torchscript_depth_model(_ToyDepth(), root, 'toy')
    return small_bag(synthetic_tum_dir, root / 'bag'), write_params(root / 'params.yaml', model)


def running(pid: int) -> bool:
    try:
        return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0] != 'Z'
    except (OSError, IndexError):
        return False


@pytest.mark.parametrize('victim', ['multi_view_node', 'single_view_node', 'fusion_node', 'bag_replayer'])
def test_kill_9_of_a_node_stops_the_run_with_a_summary(victim, setup, tmp_path):
    from rosbags.rosbag2 import Reader

    bag, params = setup
    out = tmp_path / 'out'
    cmd = [sys.executable, '-m', 'depth_fusion_ros.cli.main', 'run', '--bag', str(bag)]
    cmd += ['--params', str(params), '--processes', '--record', str(out), '--set', 'bag_replayer.loop=true']
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=os.environ.copy()
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and not any('[bag_replayer]: playing' in ln for ln in lines):
        assert proc.poll() is None, ''.join(lines)
        time.sleep(0.2)
    time.sleep(2.0)  # the bag loops: the graph is busy
    pids = dict(re.findall(r'(?:started|forked) (\w+) \(pid (\d+)\)', ''.join(lines)))
    assert set(pids) == {'multi_view_node', 'single_view_node', 'fusion_node', 'bag_replayer'}, ''.join(lines)
    os.kill(int(pids[victim]), signal.SIGKILL)
    code = proc.wait(120)
    reader.join(5)
    output = ''.join(lines)
    assert code == 1, output
    assert f'depth-fusion run: error: {victim} was killed by SIGKILL (exit -9)' in output, output
    summary = re.search(r'stopped: (\d+) of (\d+) keyframes fused before the failure \(processes\)', output)
    assert summary, output
    partial = re.search(r'partial recording \(readable\) in (\S+)', output)
    assert partial, output
    with Reader(Path(partial.group(1))) as bag_reader:  # closed properly: metadata and all
        assert bag_reader.message_count >= 0
        fused = sum(1 for c in bag_reader.connections if c.topic == '/depth_fusion/fused/depth')
        assert fused <= 1
    assert not out.exists()
    time.sleep(0.5)
    assert [n for n, p in pids.items() if running(int(p))] == []
