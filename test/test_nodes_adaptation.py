"""single_view_node adapting online over real DDS: inference never waits for training, weights
swap in, ~/save_model writes a checkpoint that loads, adapt false is bit-identical."""

from __future__ import annotations

import json
import os
import threading
import time

import numpy as np
import pytest
import rclpy
import torch
from conftest import save_torchscript_depth_model
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.parameter import Parameter
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.graph_events import READERS_DEPTH, TOPIC_READY, ReadyStatus, ready_qos
from depth_fusion_ros.nodes.posing import (
    TOPIC_POSING_TRANSFORM,
    TOPIC_REPOSED_KEYFRAMES,
    posing_qos,
    reposed_msg,
    transform_msg,
)
from depth_fusion_ros.nodes.single_view_node import SingleViewNode
from depth_fusion_ros.nodes.testing import RosHarness
from depth_fusion_ros.pose_corrections import Posing
from depth_fusion_ros.singleview.predictor import load_predictor

K = m.RCLPY
FRAME = 'camera_rgb_optical_frame'


@pytest.fixture(scope='module')
def room(small_sequence):
    return small_sequence


def _params(model: str, **extra) -> list[Parameter]:
    values = {'model': model, 'width': 160, 'height': 120, 'queue_size': 8, **extra}
    return [Parameter(k, value=v) for k, v in values.items()]


def _keyframe_publishers(ros: RosHarness) -> dict:
    """Publishers of a keyframe's parts as multi_view_node sends them to the single-view node."""
    return {
        'image': ros.publisher(Image, '/depth_fusion/keyframe/image'),
        'info': ros.publisher(CameraInfo, '/depth_fusion/keyframe/camera_info'),
        'pose': ros.publisher(PoseStamped, '/depth_fusion/keyframe/pose'),
        'depth': ros.publisher(Image, '/depth_fusion/multi_view/depth'),
        'score': ros.publisher(Image, '/depth_fusion/multi_view/score'),
    }


def _publish_keyframe(pubs: dict, room, i: int, stamp: int, signals: bool = True) -> None:
    header = m.header_msg(stamp, FRAME, kind=K)
    f = room.frames[i]
    if signals:
        pubs['pose'].publish(m.pose_stamped_msg(f.pose, m.header_msg(stamp, 'world', kind=K), kind=K))
    pubs['image'].publish(m.image_msg(f.rgb, 'rgb8', header, kind=K))
    if signals:
        gt = room.gt_depth_working(i)
        depth = np.full(gt.shape, np.nan, np.float32)
        depth[::5, ::5] = gt[::5, ::5]  # stands in for the multi-view points
        pubs['depth'].publish(m.depth_image_msg(depth, header, kind=K))
        pubs['score'].publish(
            m.depth_image_msg(np.where(np.isfinite(depth), 1.0, np.nan).astype(np.float32), header, kind=K)
        )


def _training_node(ros: RosHarness, tiny_model: str) -> SingleViewNode:
    """A single-view node that trains on every keyframe the stand-in points allow: few points,
    no baseline, no start coverage, at the inference's priority (see the first test)."""
    params = {
        'adaptation.min_points': 5,
        'adaptation.min_baseline': 0.0,
        'adaptation.start_coverage': 0.0,
        'adaptation.nice': 0,
        'adaptation.queue_size': 8,
    }
    return ros.add(SingleViewNode(context=ros.context, parameter_overrides=_params(tiny_model, **params)))


def test_inference_never_waits_for_training_and_adapted_weights_are_saved(tiny_model, room, tmp_path):
    checkpoint = tmp_path / 'adapted.pt'
    original = load_predictor(tiny_model)
    with RosHarness() as ros:
        node = ros.add(
            SingleViewNode(
                context=ros.context,
                parameter_overrides=_params(
                    tiny_model,
                    **{
                        'adaptation.checkpoint': str(checkpoint),
                        'adaptation.steps_per_keyframe': 3,
                        'adaptation.min_points': 5,
                        'adaptation.queue_size': 8,
                        'adaptation.min_baseline': 0.0,
                        # The stand-in points cover 42 % of this room's cells; coverage has
                        # its own tests (test_adaptation.py).
                        'adaptation.start_coverage': 0.0,
                        # Training at its default nice +10 got so little CPU beside a busy
                        # machine's other work that it was not yet built after 30 s (the
                        # test failed 4 of 4 beside three busy loops). The priority has its
                        # own tests; this one is about inference not waiting for training.
                        'adaptation.nice': 0,
                    },
                ),
            )
        )
        assert node.adaptation is not None  # auto: on for one of our checkpoints
        # Hold the training thread inside its first update, as a very slow update would.
        gate, entered = threading.Event(), threading.Event()
        observe = node.adaptation.adapter.observe

        def slow_observe(sample, abort=None, behind=False):
            entered.set()
            gate.wait(60)
            return observe(sample, abort, behind)

        node.adaptation.adapter.observe = slow_observe
        pubs = _keyframe_publishers(ros)
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers(list(pubs.values()))
        pubs['info'].publish(m.camera_info_msg(room.camera, m.header_msg(1, FRAME, kind=K), kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('camera_info') == 1, 10.0)
        stamps = [1_000_000_000 + i * 100_000_000 for i in range(6)]
        for i in range(4):
            _publish_keyframe(pubs, room, i, stamps[i])
        assert ros.wait_for(lambda: len(depths) >= 4, timeout=30.0), node.stats.snapshot().summary()
        # The training thread builds its optimiser first (importing torch._dynamo, 1-4 s when
        # no earlier test in this process did): wait for it to reach the held update.
        assert ros.wait_for(entered.is_set, timeout=60.0)
        assert node.adaptation.slot.version == 0  # training is stuck, inference is not
        for msg, i in zip(depths, range(4), strict=True):
            np.testing.assert_array_equal(m.image_to_numpy(msg), original.predict(room.frames[i].rgb))

        gate.set()
        assert ros.wait_for(lambda: node.adaptation.slot.version >= 2, timeout=60.0), (
            node.stats.snapshot().summary()
        )
        _publish_keyframe(pubs, room, 4, stamps[4], signals=False)
        assert ros.wait_for(lambda: len(depths) >= 5, timeout=30.0)
        adapted = m.image_to_numpy(depths[4])
        assert not np.array_equal(adapted, original.predict(room.frames[4].rgb))  # new weights swapped in

        # Training goes on through the keyframes still queued; the checkpoint is compared with
        # the weights in use after the save, and shutdown writes it again: both need the last
        # update done (1 of 2 runs failed without this wait, at HEAD edf72d5 too).
        assert node.adaptation.online.wait_idle(60.0)
        client_node = rclpy.create_node('save_client', context=ros.context)
        ros.add(client_node)
        client = client_node.create_client(Trigger, '/single_view_node/save_model')
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(Trigger.Request())
        assert ros.wait_for(future.done, timeout=30.0)
        assert future.result().success, future.result().message
        current = node.current_predictor().predict(room.frames[5].rgb)
        snap = node.stats.snapshot()

    assert snap.published['adapted_weights'] >= 2 and snap.received['keyframe_pose'] == 4
    np.testing.assert_array_equal(load_predictor(checkpoint).predict(room.frames[5].rgb), current)


@pytest.mark.parametrize('process', [True, False])
def test_the_node_is_warm_only_once_training_can_take_keyframes(tiny_model, process):
    """Ready (inference) at once, warm when the trainer is built: a replay waits for the warm
    line (bag_replayer.wait_warm), so a bag is trained on from its first keyframe."""
    with RosHarness() as ros:
        lines = ros.collect(String, '/' + TOPIC_READY, ready_qos(READERS_DEPTH))
        # nice 0: at its default +10 the trainer beside a busy machine's other work was not
        # built within the minute (1 of 2 failed beside three busy loops); this test is about
        # the order of the lines, not about the priority.
        params = _params(tiny_model, **{'adaptation.process': process, 'adaptation.nice': 0})
        node = ros.add(SingleViewNode(context=ros.context, parameter_overrides=params))
        assert node.adaptation is not None and (node.adaptation.remote is not None) == process

        def statuses() -> list[ReadyStatus]:
            return [ReadyStatus.from_json(msg.data) for msg in list(lines)]

        assert ros.wait_for(lambda: any(s.warm for s in statuses()), timeout=60.0), statuses()
        if process:
            assert node.adaptation.remote.ready
            # The process takes seconds to import torch; the node said ready long before.
            first, *rest = statuses()
            assert not first.warm and rest and rest[-1].warm
        assert all(s.node == '/single_view_node' for s in statuses())


def test_a_training_thread_warm_before_the_node_is_built_still_says_warm(tiny_model, monkeypatch):
    """The training thread (``adaptation.process`` false) can be warm before the node's
    adaptation has finished its constructor: its warm callback must find what it reads there.
    The race is made certain here (the constructor waits for the thread's warm-up); a fresh
    clone's full run once lost it (``'NodeAdaptation' object has no attribute '_stopping'``, and
    the node never said warm)."""
    import threading

    from depth_fusion_ros.nodes import single_view_adaptation

    class WarmFirst(single_view_adaptation.OnlineAdaptation):
        def __init__(self, *args, on_warm=None, **kwargs):
            called = threading.Event()

            def warm() -> None:
                try:
                    on_warm()
                finally:
                    called.set()

            super().__init__(*args, on_warm=warm, **kwargs)
            assert called.wait(60.0)  # the thread is warm before the constructor goes on

    monkeypatch.setattr(single_view_adaptation, 'OnlineAdaptation', WarmFirst)
    with RosHarness() as ros:
        lines = ros.collect(String, '/' + TOPIC_READY, ready_qos(READERS_DEPTH))
        params = _params(tiny_model, **{'adaptation.process': False, 'adaptation.nice': 0})
        node = ros.add(SingleViewNode(context=ros.context, parameter_overrides=params))
        assert node.adaptation is not None
        assert ros.wait_for(
            lambda: any(ReadyStatus.from_json(msg.data).warm for msg in list(lines)), timeout=30.0
        ), [msg.data for msg in list(lines)]


def test_adapt_false_is_the_network_as_loaded_bit_for_bit(tiny_model, room):
    reference = load_predictor(tiny_model)
    with RosHarness() as ros:
        node = ros.add(
            SingleViewNode(context=ros.context, parameter_overrides=_params(tiny_model, adapt='false'))
        )
        assert node.adaptation is None
        image = ros.publisher(Image, '/depth_fusion/keyframe/image')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([image])
        for i in range(2):
            image.publish(
                m.image_msg(room.frames[i].rgb, 'rgb8', m.header_msg(10 + i, FRAME, kind=K), kind=K)
            )
        assert ros.wait_for(lambda: len(depths) >= 2, timeout=20.0)
    for i, msg in enumerate(depths):
        np.testing.assert_array_equal(m.image_to_numpy(msg), reference.predict(room.frames[i].rgb))


def test_adapt_true_on_a_torchscript_model_fails_at_start(tmp_path):
    class Flat(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return 1.0 + 0.0 * x[:, :1]

    path = save_torchscript_depth_model(Flat(), tmp_path, 'flat')
    with RosHarness() as ros, pytest.raises(ValueError, match='cannot be adapted'):
        SingleViewNode(context=ros.context, parameter_overrides=_params(str(path), adapt='true'))


@pytest.mark.parametrize('suffix', ['.onnx', '.pt2', '.pt'])
def test_exported_models_do_not_adapt_by_default_and_refuse_adapt_true(tmp_path, suffix):
    """ONNX / torch.export / TorchScript files hold no trainable weights: auto is off for
    them, true is a one-line start-up error naming the model."""
    from depth_fusion_ros.nodes.single_view_adaptation import adaptation_wanted

    if suffix == '.pt':

        class Flat(torch.nn.Module):
            def forward(self, x: torch.Tensor) -> torch.Tensor:
                return 1.0 + 0.0 * x[:, :1]

        path = save_torchscript_depth_model(Flat(), tmp_path, 'flat')
    else:
        path = tmp_path / f'model{suffix}'
        path.write_bytes(b'not read: the suffix decides')
    assert adaptation_wanted({'adapt': 'auto', 'model': str(path)}) is False
    with pytest.raises(ValueError, match='cannot be adapted'):
        adaptation_wanted({'adapt': 'true', 'model': str(path)})
    assert adaptation_wanted({'adapt': 'auto', 'model': 'default'}) is True


def _adaptation_hearing(ros: RosHarness, tiny_model, msg_type, topic: str):
    """An adapting single_view_node, a publisher of the posing topic ``topic`` and one of the
    keyframe poses, matched."""
    node = ros.add(SingleViewNode(context=ros.context, parameter_overrides=_params(tiny_model)))
    assert node.adaptation is not None
    said = ros.publisher(msg_type, '/' + topic, posing_qos())
    poses = ros.publisher(PoseStamped, '/depth_fusion/keyframe/pose')
    assert ros.wait_for_subscribers([said, poses])
    return node, said, poses


def test_a_mount_turn_multi_view_node_takes_re_poses_the_keyframe_poses_the_adaptation_holds(
    tiny_model, room
):
    """multi_view_node says on depth_fusion/posing/camera_from_pose_frame that its mount check
    turned the camera: the adaptation's waiting keyframe poses, and one posed before the turn
    that arrives after it, are turned too, so its photometric pairs compare one camera."""
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('x', 2.0, degrees=True).as_matrix()
    with RosHarness() as ros:
        node, said, poses = _adaptation_hearing(ros, tiny_model, TransformStamped, TOPIC_POSING_TRANSFORM)
        said.publish(transform_msg(Posing(np.eye(4)), 1_000_000_000, 'camera', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing') == 1, 10.0)
        before = [1_000_000_000, 1_100_000_000]  # posed without the turn
        poses.publish(
            m.pose_stamped_msg(room.frames[0].pose, m.header_msg(before[0], 'world', kind=K), kind=K)
        )
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('keyframe_pose') == 1, 10.0)
        said.publish(transform_msg(Posing(turn), 1_150_000_000, 'camera', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing') == 2, 10.0)
        poses.publish(
            m.pose_stamped_msg(room.frames[1].pose, m.header_msg(before[1], 'world', kind=K), kind=K)
        )
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('keyframe_pose') == 2, 10.0)
        # The count comes first in the callback, the pose after it: wait for the pose too.
        assert ros.wait_for(lambda: before[1] in node.adaptation.assembler._pending, 10.0)
        waiting = {s: e.values['pose'] for s, e in node.adaptation.assembler._pending.items()}
    np.testing.assert_allclose(waiting[before[0]], room.frames[0].pose @ turn, atol=1e-12)
    np.testing.assert_allclose(waiting[before[1]], room.frames[1].pose @ turn, atol=1e-12)


def test_a_frame_turn_multi_view_node_takes_starts_the_adaptation_over(tiny_model, room):
    """multi_view_node found that the told poses were a body frame's and turned the camera by
    120 deg: every keyframe trained on before had points triangulated with the wrong motion.
    The node goes back to the loaded weights (its next depth is the loaded network's, bit for
    bit), says so, and does not train on a keyframe posed before the turn that comes later."""
    original = load_predictor(tiny_model)
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_quat([-0.5, 0.5, -0.5, 0.5]).as_matrix()  # x forward -> optical
    with RosHarness() as ros:
        node = _training_node(ros, tiny_model)
        said = ros.publisher(TransformStamped, '/' + TOPIC_POSING_TRANSFORM, posing_qos())
        pubs = _keyframe_publishers(ros)
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([said, *pubs.values()])
        pubs['info'].publish(m.camera_info_msg(room.camera, m.header_msg(1, FRAME, kind=K), kind=K))
        said.publish(transform_msg(Posing(np.eye(4)), 1_000_000_000, 'camera', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('camera_info') == 1, 10.0)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing') == 1, 10.0)
        stamps = [1_000_000_000 + i * 100_000_000 for i in range(5)]
        for i in range(3):
            _publish_keyframe(pubs, room, i, stamps[i])
        assert ros.wait_for(lambda: len(depths) >= 3, timeout=30.0)
        assert ros.wait_for(lambda: node.adaptation.slot.version >= 1, timeout=60.0), (
            node.stats.snapshot().summary()
        )
        assert node.adaptation.online.wait_idle(60.0)
        said.publish(transform_msg(Posing(frame), stamps[3], 'camera', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().noted.get('adapt_restarted') == 1, 10.0)
        assert node.adaptation.online.wait_idle(60.0)
        version = node.adaptation.slot.version
        _publish_keyframe(pubs, room, 2, stamps[2] + 50_000_000)  # posed before the turn, late
        assert ros.wait_for(lambda: node.adaptation.online.stale == 1, timeout=30.0)
        _publish_keyframe(pubs, room, 4, stamps[4], signals=False)
        assert ros.wait_for(lambda: len(depths) >= 5, timeout=30.0)
        assert node.adaptation.online.wait_idle(60.0)
        snap = node.stats.snapshot()
    np.testing.assert_array_equal(m.image_to_numpy(depths[4]), original.predict(room.frames[4].rgb))
    assert node.adaptation.slot.version == version and node.adaptation.adapter.counters.restarts == 1
    assert not node.adaptation.online.learnt  # shutdown would not write the loaded weights over a checkpoint
    assert snap.published['adapted_weights'] >= 2 and not snap.dropped


def test_keyframes_whose_points_the_fusion_trusted_none_of_are_not_trained_on(tiny_model, room):
    """fusion_node's verdict per keyframe (``fused/decision``, matched by its exact ``stamp_ns``):
    once one has come, a keyframe waits for its own, and one whose points the guard trusted none
    of (``single_view``) is skipped as ``untrusted_points``; the others train. A verdict without
    ``stamp_ns`` is a counted drop, not a crash."""
    with RosHarness() as ros:
        node = _training_node(ros, tiny_model)
        pubs = _keyframe_publishers(ros)
        verdicts = ros.publisher(String, '/depth_fusion/fused/decision')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([verdicts, *pubs.values()])
        pubs['info'].publish(m.camera_info_msg(room.camera, m.header_msg(1, FRAME, kind=K), kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('camera_info') == 1, 10.0)
        stamps = [1_796_498_280_888_172_923 + i * 100_000_000 for i in range(5)]

        def verdict(stamp: int, decision: str) -> String:
            said = {'stamp': stamp / 1e9, 'stamp_ns': stamp, 'decision': decision, 'reason': 'r'}
            return String(data=json.dumps(said))

        verdicts.publish(String(data=json.dumps({'stamp': 1.0, 'decision': 'full'})))  # no stamp_ns
        assert ros.wait_for(lambda: node.stats.snapshot().dropped.get('bad_decision') == 1, 10.0)
        verdicts.publish(verdict(stamps[0], 'single_view'))  # before its keyframe: it waits for nothing
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('fused_decision') == 2, 10.0)
        for i, decision in enumerate(['single_view', 'single_view', 'full', 'full']):
            _publish_keyframe(pubs, room, i, stamps[i])
            assert ros.wait_for(lambda i=i: len(depths) >= i + 1, timeout=30.0)
            if i:
                verdicts.publish(verdict(stamps[i], decision))
        assert ros.wait_for(lambda: node.adaptation.adapter.counters.observed >= 4, timeout=60.0), (
            node.stats.snapshot().summary()
        )
        assert node.adaptation.online.wait_idle(60.0)
        reasons = dict(node.adaptation.adapter.counters.reasons)
        version = node.adaptation.slot.version
        snap = node.stats.snapshot()
    assert reasons == {'untrusted_points': 2}, reasons
    assert version >= 1 and snap.received['fused_decision'] == 5, snap.summary()
    assert snap.dropped == {'bad_decision': 1}, snap.summary()


def test_the_keyframes_multi_view_node_reads_again_at_a_corrected_offset_move_in_the_adaptation(
    tiny_model, room
):
    """multi_view_node corrected its pose time offset and read the keyframes before it again
    (depth_fusion/posing/reposed_keyframes): the adaptation's waiting pose takes the new one,
    and so does a keyframe whose old pose comes after the message (it was in flight)."""
    late = np.eye(4)
    late[:3, 3] = (0.03, 0.0, 0.0)
    stamps = [1_000_000_000, 1_100_000_000]
    with RosHarness() as ros:
        node, reposed, poses = _adaptation_hearing(ros, tiny_model, PathMsg, TOPIC_REPOSED_KEYFRAMES)

        def pose(i: int) -> None:  # posed at the old offset
            header = m.header_msg(stamps[i], 'world', kind=K)
            poses.publish(m.pose_stamped_msg(room.frames[i].pose @ late, header, kind=K))

        pose(0)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('keyframe_pose') == 1, 10.0)
        truth = [(stamps[i], room.frames[i].pose) for i in range(2)]
        reposed.publish(reposed_msg(1_150_000_000, 'world', truth, kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('reposed_keyframes') == 1, 10.0)
        pose(1)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('keyframe_pose') == 2, 10.0)
        # The count comes first in the callback, the pose after it: wait for the pose too.
        assert ros.wait_for(lambda: stamps[1] in node.adaptation.assembler._pending, 10.0)
        waiting = {s: e.values['pose'] for s, e in node.adaptation.assembler._pending.items()}
    np.testing.assert_allclose(waiting[stamps[0]], room.frames[0].pose, atol=1e-12)
    np.testing.assert_allclose(waiting[stamps[1]], room.frames[1].pose, atol=1e-12)


def test_a_run_that_learnt_nothing_leaves_the_earlier_checkpoint_as_it_was(tiny_model, tmp_path, monkeypatch):
    """Shutdown writes the adapted weights only when an update was accepted: a run without one
    used to write the network as loaded over an earlier run's adapted checkpoint. The default
    path is under $ROS_HOME (~/.ros when unset), as ROS keeps its own files."""
    from depth_fusion_ros.nodes.single_view_adaptation import DEFAULT_CHECKPOINT, is_own_network

    monkeypatch.setenv('ROS_HOME', str(tmp_path))
    earlier = tmp_path / 'depth_fusion_ros' / 'single_view_adapted.pt'
    earlier.parent.mkdir(parents=True)
    earlier.write_bytes(b'an earlier run adapted these')
    with RosHarness() as ros:
        params = _params(tiny_model, **{'adaptation.process': False})
        node = ros.add(SingleViewNode(context=ros.context, parameter_overrides=params))
        assert node.params['adaptation.checkpoint'] == DEFAULT_CHECKPOINT
        assert node.adaptation is not None and node.adaptation.slot.version == 0
        node.adaptation.shutdown()
    assert earlier.read_bytes() == b'an earlier run adapted these'
    assert node.adaptation.save() == earlier  # ~/save_model, asked for, writes it
    # model: takes the same string, $ROS_HOME and all, and adapt: auto sees one of our networks
    assert load_predictor(DEFAULT_CHECKPOINT).predict(np.zeros((120, 160, 3), np.uint8)).shape == (120, 160)
    assert is_own_network(DEFAULT_CHECKPOINT)


@pytest.mark.skipif(not hasattr(os, 'SCHED_IDLE'), reason='SCHED_IDLE is Linux only')
def test_the_nodes_training_process_runs_under_sched_idle_unless_told_otherwise(tiny_model):
    """``adaptation.idle_policy`` (default true) reaches the training process; false leaves it
    at its niceness alone (docs/adaptation.md)."""
    for given, policy in ((None, os.SCHED_IDLE), (False, os.SCHED_OTHER)):
        extra = {} if given is None else {'adaptation.idle_policy': given}
        with RosHarness() as ros:
            params = _params(tiny_model, **extra)
            node = ros.add(SingleViewNode(context=ros.context, parameter_overrides=params))
            remote = node.adaptation.remote
            assert remote is not None and remote.idle is (given is None)
            deadline = time.monotonic() + 30.0  # the child sets it first thing, before torch
            while os.sched_getscheduler(remote.pid) != policy and time.monotonic() < deadline:
                time.sleep(0.05)
            assert os.sched_getscheduler(remote.pid) == policy
            assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the node itself is not idled
