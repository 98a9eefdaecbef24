"""Node infrastructure without a graph: parameter specs, the bounded worker, counters, inputs."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.image_input import CameraInput, InputError, pose_from_message
from depth_fusion_ros.nodes.params import (
    ParamSpec,
    build_dataclass,
    dataclass_specs,
    missing_descriptions,
    yaml_section,
)
from depth_fusion_ros.nodes.stamp_guard import StampGuard
from depth_fusion_ros.nodes.stats import NodeStats
from depth_fusion_ros.nodes.worker import BoundedWorker

# --- parameters ---------------------------------------------------------------------------------


def test_param_spec_checks_type_range_and_choices():
    assert ParamSpec('k', 5, 'every k-th', 1, 100).check(7) == 7
    with pytest.raises(ValueError, match="parameter 'k' is 0: must be >= 1"):
        ParamSpec('k', 5, 'every k-th', 1, 100).check(0)
    with pytest.raises(ValueError, match='must be an integer'):
        ParamSpec('k', 5, 'd').check(2.5)
    assert ParamSpec('sigma', 1.5, 'd', 0.0).check(2) == 2.0  # an int in YAML is a valid float
    with pytest.raises(ValueError, match='expected one of exact, fast'):
        ParamSpec('mode', 'fast', 'd', choices=('exact', 'fast')).check('slow')
    with pytest.raises(ValueError, match='must have 4 elements'):
        ParamSpec('K', [0.0] * 4, 'd', length=4).check([1.0, 2.0])
    assert ParamSpec('K', [0.0] * 4, 'd', length=4).check([1, 2, 3, 4]) == [1.0, 2.0, 3.0, 4.0]
    with pytest.raises(ValueError, match='true or false'):
        ParamSpec('flag', True, 'd').check('yes')
    # an unquoted YAML `adapt: false` is a bool; a true/false/auto string parameter takes it
    tri = ParamSpec('adapt', 'auto', 'd', choices=('auto', 'true', 'false'))
    assert (tri.check(False), tri.check(True)) == ('false', 'true')
    with pytest.raises(ValueError, match='must be a string'):
        ParamSpec('mode', 'fast', 'd', choices=('exact', 'fast')).check(True)


@dataclass
class _Config:
    num_samples: int = 64
    min_depth: float = 0.2
    mode: str = 'fast'
    align_scale: bool | None = None
    threshold: float | None = None
    table: tuple = (1, 2)


def test_dataclass_specs_round_trip_and_sentinels():
    specs = dataclass_specs(
        _Config,
        'cfg',
        {'num_samples': 'samples', 'mode': 'mode'},
        {'num_samples': (2, 512), 'mode': ('exact', 'fast')},
    )
    by_name = {s.name: s for s in specs}
    assert set(by_name) == {
        'cfg.num_samples',
        'cfg.min_depth',
        'cfg.mode',
        'cfg.align_scale',
        'cfg.threshold',
    }
    assert by_name['cfg.num_samples'].max_value == 512 and by_name['cfg.mode'].choices == ('exact', 'fast')
    assert by_name['cfg.align_scale'].default == 'auto' and by_name['cfg.threshold'].default == -1.0
    values = {s.name: s.default for s in specs}
    assert build_dataclass(_Config, values, 'cfg') == _Config()
    values.update({'cfg.align_scale': 'true', 'cfg.threshold': 0.3, 'cfg.num_samples': 96})
    cfg = build_dataclass(_Config, values, 'cfg')
    assert cfg.align_scale is True and cfg.threshold == 0.3 and cfg.num_samples == 96
    assert missing_descriptions(_Config, {'num_samples': 'x'}) == [
        'min_depth',
        'mode',
        'align_scale',
        'threshold',
    ]
    text = yaml_section('node', specs)
    assert 'node:\n  ros__parameters:\n' in text and "cfg.mode: 'fast'" in text


# --- worker -------------------------------------------------------------------------------------


def _slow_worker(policy: str, maxsize: int = 1):
    gate = threading.Event()
    handled: list[int] = []
    dropped: list[tuple[int, str]] = []

    def handle(item: int) -> None:
        gate.wait(5.0)
        handled.append(item)

    worker = BoundedWorker(
        'test', handle, maxsize=maxsize, policy=policy, on_drop=lambda i, r: dropped.append((i, r))
    )
    return worker, gate, handled, dropped


def _wait_busy(worker: BoundedWorker) -> None:
    deadline = time.monotonic() + 5.0
    while worker.pending and time.monotonic() < deadline:
        time.sleep(0.005)


def test_worker_latest_policy_keeps_the_newest():
    worker, gate, handled, dropped = _slow_worker('latest')
    worker.submit(0)
    _wait_busy(worker)  # item 0 in hand, queue empty
    for i in range(1, 5):
        assert worker.submit(i)
    gate.set()
    assert worker.wait_idle(5.0)
    worker.stop()
    assert handled == [0, 4]
    assert dropped == [(1, 'queue_full'), (2, 'queue_full'), (3, 'queue_full')]


def test_worker_drop_new_and_block_policies():
    worker, gate, handled, dropped = _slow_worker('drop_new')
    worker.submit(0)
    _wait_busy(worker)
    assert worker.submit(1) and not worker.submit(2)
    gate.set()
    worker.wait_idle(5.0)
    worker.stop()
    assert handled == [0, 1] and dropped == [(2, 'queue_full')]

    worker, gate, handled, dropped = _slow_worker('block')
    worker.submit(0)
    _wait_busy(worker)
    worker.submit(1)
    assert not worker.submit(2, timeout=0.05)  # no room within the timeout
    threading.Timer(0.1, gate.set).start()
    assert worker.submit(3, timeout=5.0)  # waits for room instead of dropping
    worker.wait_idle(5.0)
    worker.stop()
    assert handled == [0, 1, 3] and dropped == [(2, 'queue_full')]


def test_worker_survives_errors_and_stops():
    errors = []

    def handle(item: int) -> None:
        if item == 1:
            raise RuntimeError('boom')

    worker = BoundedWorker('t', handle, maxsize=4, on_error=lambda i, e: errors.append((i, str(e))))
    for i in range(3):
        worker.submit(i)
    assert worker.wait_idle(5.0)
    assert worker.stop(timeout=5.0)
    assert errors == [(1, 'boom')] and worker.handled == 2
    assert not worker.submit(9)  # after stop: dropped, never handled


def test_worker_start_runs_first_on_its_own_thread_and_items_wait_for_it():
    """A warm-up (``start``) belongs on the thread that handles the items; items submitted
    while it runs wait for it, and a failing one is logged, not fatal."""
    gate = threading.Event()
    seen: list[tuple[str, object]] = []

    def start() -> None:
        gate.wait(5.0)
        seen.append(('start', threading.current_thread().name))

    def handle(item: int) -> None:
        seen.append((f'item {item}', threading.current_thread().name))

    worker = BoundedWorker('w', handle, maxsize=4, start=start)
    assert worker.submit(1) and not worker.started.is_set()
    time.sleep(0.05)
    assert seen == []  # item 1 waits for the warm-up
    gate.set()
    assert worker.started.wait(5.0) and worker.wait_idle(5.0)
    worker.stop()
    assert seen == [('start', 'w-worker'), ('item 1', 'w-worker')]

    def broken() -> None:
        raise RuntimeError('no GPU today')

    handled: list[int] = []
    worker = BoundedWorker('b', handled.append, maxsize=4, start=broken)
    assert worker.started.wait(5.0)
    worker.submit(7)
    assert worker.wait_idle(5.0) and worker.stop()
    assert handled == [7]
    assert BoundedWorker('n', handled.append).started.wait(5.0)  # no start: started at once


# --- counters -----------------------------------------------------------------------------------


def test_stats_count_and_throttle_warnings():
    warnings: list[str] = []
    stats = NodeStats(warnings.append, throttle=60.0)
    for _ in range(5):
        stats.dropped('no_pose', 'image at 1.0 not covered')
    stats.dropped('bad_encoding', 'yuv422')
    stats.received('image')
    stats.processed(0.02)
    snap = stats.snapshot()
    assert snap.dropped == {'no_pose': 5, 'bad_encoding': 1} and snap.dropped_total == 6
    assert len(warnings) == 2 and 'no_pose' in warnings[0] and 'image at 1.0' in warnings[0]
    assert 'dropped 6' in snap.summary() and 'latency mean 20.0 ms' in snap.summary()


# --- inputs -------------------------------------------------------------------------------------


def test_stamp_guard_rejects_repeats_and_reversals():
    guard = StampGuard('image')
    guard.check(10)
    with pytest.raises(InputError) as exc:
        guard.check(10)
    assert exc.value.reason == 'duplicate_stamp_image'
    with pytest.raises(InputError) as exc:
        guard.check(5)
    assert exc.value.reason == 'stamp_out_of_order_image'
    guard.check(11)


def test_camera_input_undistorts_resizes_and_rejects_bad_images():
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    header = m.header_msg(1_000, 'cam', kind=m.RCLPY)
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    image = m.image_msg(rgb, 'rgb8', header, kind=m.RCLPY)
    inp = CameraInput(32, 24)
    with pytest.raises(InputError, match='no camera_info') as exc:
        inp.working_image(image)
    assert exc.value.reason == 'no_camera_info'
    inp.update(m.camera_info_msg(cam, header, kind=m.RCLPY))
    work = inp.working_image(image)
    assert work.rgb.shape == (24, 32, 3) and work.camera == cam.scaled(32, 24) and work.stamp_ns == 1_000
    small = m.image_msg(rgb[:24], 'rgb8', header, kind=m.RCLPY)
    with pytest.raises(InputError, match='camera_info says 64x48') as exc:
        inp.working_image(small)
    assert exc.value.reason == 'size_mismatch'
    bad = m.image_msg(rgb, 'rgb8', header, kind=m.RCLPY)
    bad.encoding = 'yuv420'
    with pytest.raises(InputError) as exc:
        inp.working_image(bad)
    assert exc.value.reason == 'bad_encoding'
    rectified = CameraInput(32, 24, rectified=True)  # no camera_info needed, just resized
    assert rectified.working_image(image).rgb.shape == (24, 32, 3)


def test_pose_errors_have_reasons():
    msg = m.pose_stamped_msg(np.eye(4), m.header_msg(0, 'world', kind=m.RCLPY), kind=m.RCLPY)
    assert np.allclose(pose_from_message(msg), np.eye(4))
    msg.pose.orientation.w = 2.0
    with pytest.raises(InputError, match='not normalised') as exc:
        pose_from_message(msg)
    assert exc.value.reason == 'bad_pose'
    msg.pose.orientation.w = float('nan')
    with pytest.raises(InputError, match='non-finite'):
        pose_from_message(msg)
