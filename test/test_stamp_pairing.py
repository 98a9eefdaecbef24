"""A stream that begins again (a bag played twice): the stamp guard and the keyframe pairer take
a large jump back for a new stream, a small one stays a dropped glitch, interleaved streams do
not restart forever."""

from __future__ import annotations

import pytest

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.input_error import InputError
from depth_fusion_ros.nodes.stamp_guard import StampGuard
from depth_fusion_ros.nodes.stamp_pairing import StampPairer

S = 1_000_000_000


def test_a_large_jump_back_is_a_new_stream_a_small_one_a_glitch():
    guard = StampGuard('image', restart_after=1.0)
    assert guard.check(100 * S) is False and guard.check(101 * S) is False
    with pytest.raises(InputError, match='older than the previous'):
        guard.check(101 * S - S // 2)  # 0.5 s back: out of order, dropped
    assert guard.check(90 * S) is True  # 11 s back: a new stream, taken
    assert guard.check(90 * S + S // 30) is False
    never = StampGuard('image')  # restart_after 0: every jump back is dropped, as before
    never.check(100 * S)
    with pytest.raises(InputError):
        never.check(10 * S)


def test_interleaved_streams_stop_restarting():
    guard = StampGuard('pose', restart_after=1.0)
    outcomes = []
    for i in range(6):  # stream A at 100 s, stream B at 200 s, alternating
        for base in (200, 100):
            try:
                outcomes.append(guard.check((base + i) * S))
            except InputError:
                outcomes.append(None)
    assert outcomes.count(True) == StampGuard.MAX_RESTARTS and outcomes[-1] is None


def _header(stamp_ns: int):
    return m.header_msg(stamp_ns, 'camera', kind=m.RCLPY)


def test_pairer_pairs_the_same_stamps_again_after_a_restart():
    done, dropped, restarts = [], [], []
    pairer = StampPairer(
        ('depth', 'pose'),
        (),
        timeout=10.0,
        max_pending=8,
        on_complete=lambda p: done.append((p.stamp_ns, p.parts['depth'])),
        on_drop=lambda reason, message: dropped.append(reason),
        restart_after=1.0,
        on_restart=lambda part, stamp_ns: restarts.append(part),
    )
    for n_pass in ('first', 'second'):
        for k in range(3):
            stamp = (10 + k) * S
            pairer.add(_header(stamp), 'depth', f'{n_pass} {k}')
            pairer.add(_header(stamp), 'pose', k)
    assert [d for _, d in done] == [f'{p} {k}' for p in ('first', 'second') for k in range(3)]
    assert dropped == [] and restarts == ['depth', 'pose']


def test_pairer_replaces_an_old_keyframe_whose_stamp_a_new_stream_reuses():
    done, dropped = [], []
    pairer = StampPairer(
        ('depth', 'pose'),
        (),
        timeout=10.0,
        max_pending=8,
        on_complete=lambda p: done.append(p.parts['depth']),
        on_drop=lambda reason, message: dropped.append(reason),
        restart_after=1.0,
    )
    pairer.add(_header(10 * S), 'depth', 'old 10')
    pairer.add(_header(12 * S), 'depth', 'old 12')  # its pose never comes: still pending
    pairer.add(_header(10 * S), 'pose', 0)
    pairer.add(_header(9 * S), 'depth', 'new 9')  # a new stream
    pairer.add(_header(12 * S), 'depth', 'new 12')  # reuses the pending stamp: replaced
    pairer.add(_header(9 * S), 'pose', 0)
    pairer.add(_header(12 * S), 'pose', 0)
    assert done == ['old 10', 'new 9', 'new 12'] and dropped == ['stream_restart']


def test_a_stamp_without_any_keyframe_part_is_not_a_lost_keyframe():
    """A single-view depth for every image of a raw camera, the multi-view parts for every
    fifth: the others are closed as not keyframes (no drop, no dropped event) once a keyframe
    part passes them. A keyframe that got one of its keyframe parts and misses another is still
    dropped as ``unpaired``."""
    done, dropped, events = [], [], []
    pairer = StampPairer(
        ('single', 'mv_depth', 'camera_info'),
        ('rgb',),
        timeout=10.0,
        max_pending=16,
        on_complete=lambda p: done.append(p.stamp_ns // S),
        on_drop=lambda reason, message: dropped.append(reason),
        on_dropped_keyframe=lambda stamp_ns, reason: events.append((stamp_ns // S, reason)),
        keyframe_parts=('mv_depth', 'camera_info', 'rgb'),
    )
    for k in range(11):
        pairer.add(_header(k * S), 'single', k)
        if k % 5 == 0 and k != 5:
            pairer.add(_header(k * S), 'camera_info', k)
            pairer.add(_header(k * S), 'mv_depth', k)
        if k == 5:  # chosen, its camera_info and image came, its depth was lost
            pairer.add(_header(k * S), 'camera_info', k)
            pairer.add(_header(k * S), 'rgb', k)
    assert done == [0, 10] and pairer.not_keyframes == 8
    assert dropped == ['unpaired'] and events == [(5, 'unpaired')]
    assert pairer.pending == {}
