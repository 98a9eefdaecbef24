"""The calibration checks' middle verdict: a fit past the threshold whose error leaves it unsure
is ``suspect``, said with its numbers and never taken, not "agrees" (found when the focal check
said "fx 288.8 px agrees" of -6.7 +- 1.4 % on a camera_info 10 % long)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.cli.recordings import verdict_status
from depth_fusion_ros.evaluation.check_tables import time_offset_table
from depth_fusion_ros.evaluation.time_offset import estimate_json
from depth_fusion_ros.multiview import time_offset_check
from depth_fusion_ros.multiview.mount_check import MountCheck, MountCheckConfig
from depth_fusion_ros.multiview.time_offset_check import (
    TimeOffsetCheck,
    TimeOffsetCheckConfig,
    TimeOffsetEstimate,
)
from depth_fusion_ros.nodes.time_offset_check_runner import TimeOffsetCheckRunner

CAMERA = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)


def _offset_verdict(monkeypatch, offset: float, stderr: float):
    monkeypatch.setattr(time_offset_check, 'estimate_offset', lambda grid, curves: (offset, stderr, 1.0))
    check = TimeOffsetCheck(CAMERA, TimeOffsetCheckConfig())
    check.curves = [(np.zeros(3), 100)]
    return check._estimate()


def test_a_time_offset_past_the_threshold_but_not_surely_is_suspect(monkeypatch):
    verdicts = {
        o: _offset_verdict(monkeypatch, o, s).verdict
        for o, s in ((0.018, 0.003), (0.008, 0.002), (0.03, 0.003))
    }
    assert verdicts == {0.018: 'suspect', 0.008: 'consistent', 0.03: 'disagrees'}
    suspect = _offset_verdict(monkeypatch, 0.018, 0.003)
    message = suspect.message()
    assert '+18 +- 3 ms' in message and 'kept' in message and 'agrees' not in message
    assert verdict_status('check-sync', 'seq', suspect, 12, TimeOffsetCheckConfig(), 100) == 5


def _mount_verdict(turn_deg: float, sd_deg: float):
    cov = np.diag(np.radians([sd_deg, 0.05, 0.05]) ** 2)
    return MountCheck(CAMERA, MountCheckConfig())._verdict(np.radians([turn_deg, 0.0, 0.0]), cov)


def test_a_mount_turn_past_the_threshold_but_not_surely_is_suspect_and_not_applied():
    verdicts = {t: _mount_verdict(t, 0.1).verdict for t in (0.6, 0.3, 1.0)}
    assert verdicts == {0.6: 'suspect', 0.3: 'consistent', 1.0: 'disagrees'}
    suspect = _mount_verdict(0.6, 0.1)
    assert suspect.angle_deg == pytest.approx(0.6)
    assert np.array_equal(suspect.rotation(), np.eye(4))  # said, not applied
    message = suspect.message()
    assert 'turned 0.60 deg' in message and 'kept' in message and 'agrees' not in message
    assert not math.isclose(_mount_verdict(1.0, 0.1).rotation()[1, 1], 1.0)


def test_an_unobservable_time_offset_is_said_without_a_fitted_offset_to_copy():
    """A flat fit (smooth motion) lands wherever the noise puts it, often the search's edge:
    the log line and the diagnostics say flat, and the told offset kept, never "+100 ms"."""
    runner = TimeOffsetCheckRunner(TimeOffsetCheckConfig(), 0.0, lambda *_: None)
    runner._check = TimeOffsetCheck(CAMERA, TimeOffsetCheckConfig())
    flat = TimeOffsetEstimate(0.1, 0.005, 8, 900, 'unobservable', 0.0, sharpness=0.001)
    runner._check.result = flat
    assert runner.status() == 'unobservable: flat over 8 pairs (pose_time_offset 0.000 kept)'
    assert '100' not in flat.message() and 'kept, unchecked' in flat.message()
    loose = TimeOffsetEstimate(0.03, 0.02, 20, 900, 'unobservable', 0.0, sharpness=0.05)
    runner._check.result = loose
    assert runner.status() == 'unobservable: +30 +- 20 ms (pose_time_offset 0.000 kept)'
    assert '+30 +- 20 ms over 20 pairs' in loose.message()


def test_the_evaluation_report_says_a_flat_time_offset_fit_as_flat():
    """The report's table too (found on a synthetic hall driven forward: "-100 +- 50" of a
    flat fit at the search's edge): a flat fit is said flat; a loose one keeps its numbers."""
    flat = TimeOffsetEstimate(-0.1, 0.05, 8, 256, 'unobservable', 0.0, sharpness=0.0)
    loose = TimeOffsetEstimate(0.03, 0.02, 20, 900, 'unobservable', 0.0, sharpness=0.05)
    doc = {
        'sequences': {
            'hall': {'time_offset_check': estimate_json(flat, corrected=False)},
            'room': {'time_offset_check': estimate_json(loose, corrected=False)},
        }
    }
    assert doc['sequences']['hall']['time_offset_check']['flat'] is True
    rows = time_offset_table(doc).splitlines()
    hall, room = [line for line in rows if line.startswith(('| hall', '| room'))]
    assert 'flat' in hall and '-100' not in hall and hall.endswith('| 8 | +0 |')
    assert '+30 +- 20' in room and 'flat' not in room
