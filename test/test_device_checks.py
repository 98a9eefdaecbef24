"""A torch device the machine lacks is a one-line error at start, in every node and command:
``fusion_node -p device:=cuda`` on a CPU build once started and failed its compilation in the
background, ``device:=gpu`` ended a thread in a traceback, ``map_node`` died in one, and
``adapt`` / ``bench`` / ``evaluate --single-view simulated`` raised torch's own errors."""

from __future__ import annotations

import pytest
import torch
from rclpy.parameter import Parameter

from depth_fusion_ros.cli.main import main
from depth_fusion_ros.nodes.testing import RosHarness
from depth_fusion_ros.torch_device import resolve_device

NO_CUDA = not torch.cuda.is_available()


def test_a_typo_absent_cuda_and_a_missing_index_are_named(monkeypatch):
    assert resolve_device('cpu') == torch.device('cpu')
    with pytest.raises(ValueError, match=r"device must be 'cpu', 'cuda' or 'cuda:N', got 'gpu'"):
        resolve_device('gpu')
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: False)
    with pytest.raises(
        ValueError, match="device 'cuda' requested but CUDA is not available in this torch build"
    ):
        resolve_device('cuda')
    monkeypatch.setattr(torch.cuda, 'is_available', lambda: True)
    monkeypatch.setattr(torch.cuda, 'device_count', lambda: 1)
    assert resolve_device('cuda:0') == torch.device('cuda:0')
    with pytest.raises(
        ValueError, match=r"device 'cuda:1' requested but this machine has 1 CUDA device\(s\)"
    ):
        resolve_device('cuda:1')


def _nodes():
    from depth_fusion_ros.nodes.fusion_node import FusionNode
    from depth_fusion_ros.nodes.map_node import MapNode
    from depth_fusion_ros.nodes.multi_view_node import MultiViewNode
    from depth_fusion_ros.nodes.single_view_node import SingleViewNode

    return {
        'fusion_node': FusionNode,
        'multi_view_node': MultiViewNode,
        'map_node': MapNode,
        'single_view_node': SingleViewNode,
    }


@pytest.mark.parametrize('name', ['fusion_node', 'multi_view_node', 'map_node', 'single_view_node'])
def test_every_node_refuses_a_device_it_cannot_use_by_name(name):
    node_class = _nodes()[name]
    devices = ['gpu'] + (['cuda'] if NO_CUDA else [])
    with RosHarness() as ros:
        for device in devices:
            with pytest.raises(ValueError, match=rf"^{name}: device .*'{device}'"):
                node_class(context=ros.context, parameter_overrides=[Parameter('device', value=device)])


@pytest.mark.parametrize(
    'argv',
    [
        ['adapt', 'SEQ', '--out', 'a.pt', '--device', 'gpu'],
        ['bench', '--only', 'fusion', '--device', 'gpu'],
        ['evaluate', 'SEQ', '--single-view', 'simulated', '--device', 'gpu'],
        ['train', 'SEQ', '--out', 't.pt', '--device', 'gpu'],
    ],
)
def test_every_command_checks_its_device_before_its_work(argv, tmp_path, capsys):
    argv = [str(tmp_path) if a == 'SEQ' else a for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"depth-fusion {argv[0]}: error: device must be 'cpu', 'cuda' or 'cuda:N', got 'gpu'"
    assert 'Traceback' not in '\n'.join(err)
