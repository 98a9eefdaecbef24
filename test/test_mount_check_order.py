"""multi_view_node's mount check collects from the start and waits for the time offset check.

Why: a time offset fakes a turn, so the mount's verdict may only be said and taken once the
time offset check has settled. Until 2026-11-30 the mount check began collecting only then,
and a short stream (the `mount_tilt` stress streams: 1.5 m) ended before its pairs were in.
Now it collects from the first frame; its verdict waits; an offset correction starts it over.
These are the rules of ``nodes/multi_view_checks.py``'s ``CheckCorrections``, driven here with
stand-ins for the check runners (the node over DDS: test_nodes_mount_check.py).
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.multiview.mount_check import MountEstimate
from depth_fusion_ros.nodes.multi_view_checks import CheckCorrections
from depth_fusion_ros.nodes.stats import NodeStats

CAMERA = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)


class _Runner:
    """What CheckCorrections reads of a check runner."""

    def __init__(self) -> None:
        self.config = SimpleNamespace(mode='correct')
        self.result = None
        self.rotation = np.eye(4)
        self.correction = 0.0
        self.restarts = 0

    @property
    def settled(self) -> bool:
        return self.result is not None

    def restart(self) -> None:
        self.restarts += 1
        self.result = None


class _Node(CheckCorrections):
    def __init__(self) -> None:
        self.lines: list[str] = []
        self.params = {'pose_time_offset': 0.0}
        self.stats = NodeStats(self.lines.append)
        self.T_pose_cam = np.eye(4)
        self.focal_check, self.time_offset_check, self.mount_check = _Runner(), _Runner(), _Runner()
        self._offset_correction = 0.0
        self._mount_correction = np.eye(4)
        self._mount_taken = None
        self._mount_unsaid = None
        self._mount_unsaid_lock = threading.Lock()
        self._restart_from_ns = None

    def get_logger(self):
        return SimpleNamespace(info=self.lines.append)


def _turned(verdict: str = 'disagrees') -> MountEstimate:
    rotvec = (-2.0, 0.0, 0.0) if verdict == 'disagrees' else (0.0, 0.0, 0.0)
    return MountEstimate(rotvec, rotvec, (0.1, 0.2, 1.0), 2, 8, 2000, verdict)


def _result_arrives(node: _Node, estimate: MountEstimate) -> None:
    node.mount_check.result = estimate
    node.mount_check.rotation = estimate.rotation()
    node._on_mount_estimate(CAMERA, estimate)  # from the check's thread


def test_a_turn_found_before_the_time_offset_check_settles_is_taken_once_it_has():
    node = _Node()
    _result_arrives(node, _turned())
    node._take_offset_correction()
    node._take_mount_correction()
    assert np.array_equal(node._mount_correction, np.eye(4)) and node._restart_from_ns is None
    node.time_offset_check.result = SimpleNamespace(message=lambda: 'no offset')  # settled, no correction
    node._take_offset_correction()
    node._take_mount_correction()
    assert node._mount_correction[1, 2] != 0.0 and node._restart_from_ns == 0  # turned about x
    assert node.stats.snapshot().noted == {'mount_disagrees': 1}
    node._take_mount_correction()  # taken once
    assert node.stats.snapshot().noted == {'mount_disagrees': 1} and node.mount_check.restarts == 0


def test_an_offset_correction_starts_the_mount_check_over_and_drops_its_early_verdict():
    node = _Node()
    _result_arrives(node, _turned())
    node.time_offset_check.result = SimpleNamespace(message=lambda: 'images fit the poses 20 ms later')
    node.time_offset_check.correction = -0.02
    node._take_offset_correction()
    node._take_mount_correction()
    assert node.mount_check.restarts == 1 and node.mount_check.result is None
    assert np.array_equal(node._mount_correction, np.eye(4))
    assert set(node.stats.snapshot().noted) == {'time_offset_disagrees'}


def test_an_agreeing_verdict_is_said_once_when_the_offset_has_settled():
    node = _Node()
    _result_arrives(node, _turned('consistent'))
    assert not any('mount check' in line for line in node.lines)
    node.time_offset_check.result = SimpleNamespace(message=lambda: 'in sync')
    node._take_mount_correction()
    node._take_mount_correction()
    said = [line for line in node.lines if 'mount check' in line]
    assert len(said) == 1 and 'agrees' in said[0], node.lines
    late = _Node()  # a verdict after the offset settled is said at once, on the check's thread
    late.time_offset_check.result = SimpleNamespace(message=lambda: 'in sync')
    _result_arrives(late, _turned('consistent'))
    assert len([line for line in late.lines if 'mount check' in line]) == 1
