"""Diagnostic levels and messages, and the mixed-source watch, without DDS (pure functions)."""

from __future__ import annotations

from types import SimpleNamespace

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.diagnostics import (
    ERROR,
    OK,
    WARN,
    Diagnostics,
    Requirement,
    assess,
    missing_inputs,
)
from depth_fusion_ros.nodes.input_watch import InputWatch
from depth_fusion_ros.nodes.stats import StatsSnapshot

POSE = Requirement('pose', 'image', '/camera/pose')


def test_missing_input_only_while_the_needing_stream_arrives() -> None:
    first, last = {'image': 0.0}, {'image': 9.5}
    assert missing_inputs([POSE], first, last, now=10.0, timeout=5.0) == [
        'no pose yet while image arrives (/camera/pose)'
    ]
    assert missing_inputs([POSE], first, last, now=4.0, timeout=5.0) == []  # not long enough yet
    assert missing_inputs([POSE], first, {'image': 2.0}, now=10.0, timeout=5.0) == []  # images stopped too
    stale = missing_inputs([POSE], first, {'image': 9.5, 'pose': 3.0}, now=10.0, timeout=5.0)
    assert stale == ['no pose for 7.0 s while image arrives (/camera/pose)']


def test_levels_error_over_warn_over_ok() -> None:
    assert assess(0.0, 0.1, [], True, '').level == OK
    warn = assess(0.5, 0.1, [], False, 'camera_info', ['two sources'])
    assert warn.level == WARN
    assert warn.message == (
        '50% of the recent inputs dropped (more than 10%); not ready: waiting for camera_info; two sources'
    )
    assert assess(0.5, 0.1, ['no pose yet'], True, '').level == ERROR


def test_drop_share_is_measured_over_the_recent_window() -> None:
    diag = Diagnostics('x', 'cpu', max_share=0.1, timeout=5.0)
    snap = lambda received, dropped: StatsSnapshot(received={'image': received}, dropped={'r': dropped})  # noqa: E731
    args = ({}, {}), [], 0, True, '', {}
    diag.array(None, snap(100, 50), *args, now=0.0)
    assert diag.last_assessment.level == WARN  # 50 % since start
    diag.array(None, snap(200, 50), *args, now=5.0)
    diag.array(None, snap(300, 50), *args, now=11.0)
    assert diag.last_assessment.level == OK  # nothing dropped in the last 10 s


def test_input_watch_flags_interleaving_and_frame_changes_once() -> None:
    warnings: list[str] = []
    watch = InputWatch(warnings.append)

    def msg(sec: float, frame: str = 'cam') -> SimpleNamespace:
        return SimpleNamespace(
            header=SimpleNamespace(stamp=m.time_msg(m.sec_to_ns(sec), kind=m.RCLPY), frame_id=frame)
        )

    for t in (1.0, 2.0, 1.5, 3.0):  # one glitch: not a second stream
        watch.observe('/a', msg(t))
    assert warnings == []
    for t in (10.0, 4.0, 11.0, 5.0, 12.0, 6.0, 13.0, 7.0):
        watch.observe('/a', msg(t))
    assert len(warnings) == 1 and 'went backwards 3 times' in warnings[0] and 'ROS_DOMAIN_ID' in warnings[0]
    watch.observe('/b', msg(1.0, 'cam_a'))
    watch.observe('/b', msg(2.0, 'cam_b'))
    watch.observe('/b', msg(3.0, 'cam_c'))
    assert len(warnings) == 2 and "from 'cam_a' to 'cam_b'" in warnings[1]
    watch.observe('/c', SimpleNamespace(data='no header'))  # ignored
    assert set(watch.findings) == {'/a interleaved', '/b frames'}
