"""Each ``depth-fusion run`` on its own free ROS domain with localhost-only discovery.

The end-to-end test starts two runs of the CLI at the same time on two bags with different
stamps. Before isolation both shared the caller's domain, and the second recording held the
first run's frames; now each recording holds only its own bag's stamps.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys

import pytest

from depth_fusion_ros.nodes.graph import isolation
from depth_fusion_ros.nodes.graph.isolation import (
    PRIVATE_DOMAINS,
    RANGE_ENV,
    domain_ports,
    isolate,
    pick_free_domain,
)

pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')
torch = pytest.importorskip('torch')

from conftest import save_torchscript_depth_model  # noqa: E402
from run_bags import header_stamps, shifted_copy, small_bag, write_params  # noqa: E402

FUSED = '/depth_fusion/fused/depth'
IMAGE = '/camera/rgb/image_color'


def test_private_domain_is_free_locked_and_restored():
    env = {'ROS_DOMAIN_ID': '47'}
    first = isolate(env=env)
    try:
        assert first.private and first.localhost_only and first.domain in PRIVATE_DOMAINS
        assert env['ROS_DOMAIN_ID'] == str(first.domain) and env[RANGE_ENV] == 'LOCALHOST'
        other_env: dict[str, str] = {}
        with isolate(env=other_env) as second:  # a concurrent run never gets the same domain
            assert second.domain != first.domain
    finally:
        first.close()
    assert env == {'ROS_DOMAIN_ID': '47'}  # the caller's environment is back


def test_domain_used_by_a_participant_on_this_host_is_skipped():
    used, free = 218, 219
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(('0.0.0.0', domain_ports(used)[1]))  # like participant 0 of domain 218
        except OSError:
            pytest.skip('port of domain 218 busy on this machine')
        assert isolation.domain_in_use(used)
        domain, lock = pick_free_domain([used, free])
        lock.close()
    assert domain == free


def test_domain_id_joins_on_purpose_without_localhost_restriction():
    env = {'ROS_DOMAIN_ID': '47'}
    with isolate(domain_id=5, env=env) as iso:
        assert (iso.domain, iso.private, iso.localhost_only) == (5, False, False)
        assert env == {'ROS_DOMAIN_ID': '5'}
    with isolate(domain_id=5, localhost_only=True, env=env) as iso:
        assert env[RANGE_ENV] == 'LOCALHOST' and iso.localhost_only
    with pytest.raises(ValueError, match='--domain-id must be between 0 and 232'):
        isolate(domain_id=300, env=env)


class _ToyDepth(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 + 0.5 * torch.sigmoid(x.mean(dim=1, keepdim=True))


def run_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, '-m', 'depth_fusion_ros.cli.main', 'run', *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env or os.environ.copy(),
    )


def test_two_concurrent_runs_record_only_their_own_bag(synthetic_tum_dir, tmp_path):
    model = save_torchscript_depth_model(_ToyDepth(), tmp_path, 'toy')
    params = write_params(tmp_path / 'params.yaml', model)
    bag_a = small_bag(synthetic_tum_dir, tmp_path / 'a')
    bag_b = shifted_copy(bag_a, tmp_path / 'b', shift_ns=1000 * 10**9)
    stamps = {'a': header_stamps(bag_a, IMAGE), 'b': header_stamps(bag_b, IMAGE)}
    assert not stamps['a'] & stamps['b']
    procs = {
        name: run_cli('--bag', str(bag), '--params', str(params), '--record', str(tmp_path / f'out_{name}'))
        for name, bag in (('a', bag_a), ('b', bag_b))
    }
    outputs = {name: p.communicate(timeout=400)[0] for name, p in procs.items()}
    domains = {}
    for name, p in procs.items():
        assert p.returncode == 0, outputs[name]
        domains[name] = re.search(r'ROS domain (\d+) \(a free one, localhost-only', outputs[name]).group(1)
        assert re.search(rf' fused, .*on ROS domain {domains[name]}\b', outputs[name]), outputs[name]
    assert domains['a'] != domains['b']
    for name, other in (('a', 'b'), ('b', 'a')):
        fused = header_stamps(tmp_path / f'out_{name}', FUSED)
        assert fused, f'run {name} recorded nothing:\n{outputs[name]}'
        assert fused <= stamps[name], f'run {name} recorded foreign stamps {sorted(fused - stamps[name])}'
        assert not fused & stamps[other]


def test_two_test_harnesses_never_hear_each_other():
    # Each RosHarness takes a free domain of its own: a latched line published in one (a ready
    # line, an announced output kind) must not reach the nodes under test in another.
    from std_msgs.msg import String

    from depth_fusion_ros.nodes.graph_events import ready_qos
    from depth_fusion_ros.nodes.testing import RosHarness

    with RosHarness() as first, RosHarness() as second:
        assert first.domain_id != second.domain_id
        announcer = first.publisher(String, '/depth_fusion/single_view/output_kind', ready_qos())
        announcer.publish(String(data='relative_depth'))
        own = first.collect(String, '/depth_fusion/single_view/output_kind', ready_qos())
        other = second.collect(String, '/depth_fusion/single_view/output_kind', ready_qos())
        assert first.wait_for(lambda: len(own) == 1, 10.0)
        assert not second.wait_for(lambda: len(other) > 0, 2.0)  # four announcement periods
