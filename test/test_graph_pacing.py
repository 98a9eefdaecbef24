"""Lossless replay, readiness and the honest summary, over real DDS.

* A paced replay (the default of ``depth-fusion run``) into a graph far slower than the replay
  (every frame a keyframe, played at 10x the recorded rate, one-slot work queues) fuses every
  keyframe the policy chose; the same replay with ``realtime`` loses keyframes and the
  summary counts each one by node and reason.
* multi_view_node announces every chosen keyframe, also those its worker drops before
  announcing them (``worker_queue_full``), and says when it is ready (transient-local line
  naming its subscriptions).
* Images that come before the first camera_info wait for it instead of being dropped.

Kept cheap: 160x120 working grid, a toy TorchScript network, eager fusion kernels.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')
torch = pytest.importorskip('torch')

from conftest import save_torchscript_depth_model  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header, String  # noqa: E402

from depth_fusion_ros.data import messages as m  # noqa: E402
from depth_fusion_ros.nodes.graph import RunOptions, run_graph  # noqa: E402
from depth_fusion_ros.nodes.graph.options import RunResult  # noqa: E402
from depth_fusion_ros.nodes.graph.summary import drop_reasons, keyframe_summary  # noqa: E402
from depth_fusion_ros.nodes.graph_events import (  # noqa: E402
    READERS_DEPTH,
    TOPIC_KEYFRAME_EVENTS,
    TOPIC_READY,
    KeyframeLedger,
    ReadyStatus,
    events_qos,
    ready_qos,
)
from depth_fusion_ros.nodes.multi_view_node import MultiViewNode  # noqa: E402
from depth_fusion_ros.nodes.qos import qos_profile  # noqa: E402
from depth_fusion_ros.nodes.testing import RosHarness  # noqa: E402

pytestmark = pytest.mark.usefixtures('one_torch_thread')

FRAME = 'camera_rgb_optical_frame'
SMALL = {'width': 160, 'height': 120}


class _ToyDepth(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 + 0.5 * torch.sigmoid(x.mean(dim=1, keepdim=True))


@pytest.fixture(scope='module')
def toy_model(tmp_path_factory):
    return save_torchscript_depth_model(_ToyDepth(), tmp_path_factory.mktemp('toy'), 'toy')


@pytest.fixture(scope='module')
def bag(synthetic_tum_dir, tmp_path_factory):
    from depth_fusion_ros.data.rosbag_convert import tum_to_rosbag

    return tum_to_rosbag(
        synthetic_tum_dir, tmp_path_factory.mktemp('pacing') / 'synth.bag', show_progress=False
    ).path


def _slow_graph(bag, toy_model, realtime: bool) -> RunOptions:
    """Every posed frame a keyframe, 10x the recorded rate, one-slot queues: far too fast.

    The queue policy is left to the runner: the nodes' default ('latest': drop the oldest)
    in real time, 'block' when paced.
    """
    common = {'stats_period': 0.0, 'queue_size': 1}
    return RunOptions(
        bag=bag,
        rate=10.0,
        realtime=realtime,
        single_view_model=str(toy_model),
        overrides={
            'multi_view_node': {**common, **SMALL, 'keyframe_every': 1},
            'single_view_node': {**common, **SMALL},
            'fusion_node': {
                **common,
                'fusion.compile_kernel': False,
                'publish_points': False,
                'pair_timeout': 60.0,
            },
        },
        flush_timeout=120.0,
    )


def test_paced_replay_fuses_every_keyframe_of_a_slow_graph(bag, toy_model):
    result = run_graph(_slow_graph(bag, toy_model, realtime=False))
    print(keyframe_summary(result, 'composed'))
    assert len(result.chosen) >= 15  # 24 frames, every one but the first (no neighbour yet)
    assert result.drops == {} and result.missing == {}
    assert sorted(result.fused) == result.chosen
    assert result.images_handled == result.images_played == 24  # every image reached the policy
    assert result.paced and set(result.ready_seconds) == {
        'single_view_node',
        'multi_view_node',
        'fusion_node',
    }


def _poses_later(bag, out, lag_ns: int):
    """``bag`` with every pose recorded ``lag_ns`` after its stamp, as a SLAM publishes it."""
    from rosbags.rosbag2 import Reader

    from depth_fusion_ros.data.bag_writer import AtomicBagWriter

    pose = 'geometry_msgs/msg/PoseStamped'
    with Reader(bag) as reader:
        rows = [
            (t + (lag_ns if c.msgtype == pose else 0), c.topic, c.msgtype, bytes(raw))
            for c, t, raw in reader.messages()
        ]
    with AtomicBagWriter(out) as writer:
        for t, topic, msgtype, raw in sorted(rows, key=lambda row: row[0]):
            writer.write_raw(topic, msgtype, t, raw)
    return out


def test_a_paced_replay_of_poses_that_lag_their_images_never_stalls(bag, tmp_path):
    """Poses recorded 0.3 s (9 frames) after their images: only more images bring each pose,
    so images waiting for theirs must not hold the replay back. Until 2026-12-01 they did,
    and the replay stalled until ``pace_timeout`` switched pacing off."""
    from depth_fusion_ros.nodes.bag_replayer import BagReplayer

    lagged = _poses_later(bag, tmp_path / 'lagged', int(0.3e9))
    with RosHarness() as ros:
        node = _mv_node(ros, keyframe_every=5)
        params = {'bag': str(lagged), 'pace': True, 'pace_timeout': 10.0, 'rate': 4.0, 'linger': 0.5}
        # No fusion node here: keyframes in flight must not hold the replay back either.
        params.update(wait_ready=[node.get_name()], max_keyframes_in_flight=1000)
        replayer = BagReplayer(
            context=ros.context,
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
            autostart=False,
        )
        ros.add(replayer)
        replayer.start()
        assert replayer.finished.wait(60.0), 'the replay did not finish'
        assert ros.wait_for(lambda: node.posed_count == 24, 10.0), node.stats.snapshot().summary()
        assert node.wait_idle(30.0)
        stats = replayer.pacer.stats
    assert replayer.error is None and not stats.gave_up  # paced to the end
    assert 'no_pose' not in node.stats.snapshot().dropped


def test_realtime_replay_reports_every_drop(bag, toy_model):
    result = run_graph(_slow_graph(bag, toy_model, realtime=True))
    summary = keyframe_summary(result, 'composed')
    print(summary)
    reasons = drop_reasons(result)
    # Every chosen keyframe is accounted for: fused, or dropped by a named node and reason.
    assert len(result.fused) + sum(reasons.values()) == len(result.chosen)
    assert 'unaccounted' not in reasons
    assert reasons.get('multi_view.worker_queue_full', 0) > 0, summary
    assert f'{len(result.chosen)} keyframes chosen, {len(result.fused)} fused' in summary
    assert 'real time' in summary
    # The multi-view node's own counter agrees with what the summary says it dropped.
    counted = result.node_stats['multi_view_node'].dropped.get('worker_queue_full', 0)
    assert reasons['multi_view.worker_queue_full'] == counted


def test_summary_counts_drops_before_announcement():
    """The case of issue 13: 29 chosen, 9 dropped by multi_view_node before announcing."""
    chosen = list(range(29))
    result = RunResult(
        announced=chosen[9:],
        fused=chosen[9:],
        missing={},
        recorded=None,
        counts={},
        seconds=5.0,
        chosen=chosen,
        drops={s: 'multi_view.worker_queue_full' for s in chosen[:9]},
        paced=False,
    )
    line = keyframe_summary(result, 'processes')
    assert line.startswith('29 keyframes chosen, 20 fused, 9 dropped (multi_view.worker_queue_full=9)')


def test_ledger_first_final_event_wins_and_counts_in_flight():
    ledger = KeyframeLedger()
    for stamp in (1, 2, 3):
        ledger.add(stamp, 'chosen')
    ledger.add(1, 'fused')
    ledger.add(1, 'dropped:fusion.late_part')  # a straggler after fusion changes nothing
    ledger.add(2, 'dropped:multi_view.worker_queue_full')
    assert ledger.in_flight() == 1
    snap = ledger.snapshot()
    assert snap.fused == [1] and snap.in_flight == [3]
    assert snap.drop_reasons() == {'multi_view.worker_queue_full': 1}


class _NoNode:
    """What the pacer needs of a node: somewhere to subscribe (the test feeds its ledger)."""

    def create_subscription(self, *args, **kwargs) -> None:
        return None


def _pacer(**kwargs):
    import threading

    from depth_fusion_ros.nodes.pacer import Pacer

    warnings: list[str] = []
    options = {'max_keyframes': 1, 'max_images_ahead': 4, 'timeout': 30.0}
    pacer = Pacer(_NoNode(), stop=threading.Event(), warn=warnings.append, **{**options, **kwargs})
    return pacer, warnings


def test_a_paced_replay_waits_for_the_filter_but_not_for_a_lagging_pose():
    """The next image waits until multi_view_node has the last one and its filter is done with
    every image it posed (the next keyframe never queues behind earlier frames); images
    waiting for their pose hold nothing back (only more images bring a lagging pose);
    ``max_images_ahead`` bounds the images that never arrived; a lost image holds the replay
    back for ``SETTLE_LIMIT_S`` only."""
    from depth_fusion_ros.nodes.pacer import SETTLE_LIMIT_S

    pacer, warnings = _pacer()
    ledger = pacer.ledger
    assert pacer._busy() == ''
    pacer.sent_image(10)
    assert 'not reached' in pacer._busy()  # on its way
    ledger.add(10, 'image')  # posed: in the filter's hands
    assert 'filter' in pacer._busy()
    ledger.add(10, 'image_done')
    assert pacer._busy() == ''
    for stamp in (20, 30, 40):  # a pose stream that lags: each image waits for its pose
        pacer.sent_image(stamp)
        ledger.add(stamp, 'image_waiting')
        assert pacer._busy() == ''
    pacer.sent_image(50)
    ledger.add(50, 'image_waiting')
    assert pacer._busy() == ''  # four waiting for poses that only more images bring: no stall
    for stamp in (60, 70, 80, 90):  # lost on the way: max_images_ahead bounds those
        pacer.sent_image(stamp)
    assert 'have not reached' in pacer._busy(SETTLE_LIMIT_S)
    for stamp in (20, 30, 40, 50, 60, 70, 80, 90):  # the poses came: all posed, the filter on them
        ledger.add(stamp, 'image')
    assert 'filter' in pacer._busy()
    assert pacer._busy(SETTLE_LIMIT_S) == ''  # a filter that never says done holds it so long only
    ledger.add(90, 'image_done')
    assert pacer._busy() == ''
    pacer.sent_image(100)  # lost on the way
    assert pacer._busy(SETTLE_LIMIT_S) == ''
    ledger.add(100, 'chosen')  # a keyframe in flight holds it back whatever the filter does
    ledger.add(100, 'image')
    ledger.add(100, 'image_done')
    assert 'keyframes in flight' in pacer._busy(SETTLE_LIMIT_S)
    ledger.add(100, 'fused')
    assert pacer._busy() == '' and warnings == []


def test_ledger_keeps_the_newest_image_stamps_in_order():
    from depth_fusion_ros.nodes.graph_events import RECENT_IMAGES

    ledger = KeyframeLedger()
    assert ledger.image_ns() == -1
    for stamp in (30, 10, 20):  # a dropped image may be acknowledged before an older posed one
        ledger.add(stamp, 'image')
    assert [ledger.image_ns(back) for back in (1, 2, 3, 4)] == [30, 20, 10, -1]
    for stamp in range(100, 100 + 2 * RECENT_IMAGES):
        ledger.add(stamp, 'image')
    assert ledger.image_ns(RECENT_IMAGES) == 100 + RECENT_IMAGES and ledger.image_ns(RECENT_IMAGES + 1) == -1
    assert ledger.snapshot().images == 3 + 2 * RECENT_IMAGES  # every image counted once


# --- multi_view_node alone ------------------------------------------------------------------------


def _mv_node(ros: RosHarness, **params) -> MultiViewNode:
    values = {
        'stats_period': 0.0,
        'filter.max_lag_frames': 0,
        'filter.max_update_rate': 0.0,
        **SMALL,
        **params,
    }
    return ros.add(
        MultiViewNode(
            context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]
        )
    )


def _publishers(ros: RosHarness):
    deep = qos_profile('reliable', 100)
    pubs = (
        ros.publisher(Image, '/camera/rgb/image_color', deep),
        ros.publisher(CameraInfo, '/camera/rgb/camera_info', deep),
        ros.publisher(PoseStamped, '/camera/pose', deep),
    )
    assert ros.wait_for_subscribers(list(pubs))
    return pubs


def _events(ros: RosHarness) -> list:
    return ros.collect(Header, '/' + TOPIC_KEYFRAME_EVENTS, events_qos())


def test_ready_line_and_images_before_camera_info_wait(synthetic_sequence):
    seq = synthetic_sequence
    with RosHarness() as ros:
        node = _mv_node(ros, keyframe_every=2)
        # A reader joining after the node is ready still hears its line (transient local).
        ready = ros.collect(String, '/' + TOPIC_READY, ready_qos(READERS_DEPTH))
        events = _events(ros)
        image_pub, info_pub, pose_pub = _publishers(ros)
        assert ros.wait_for(lambda: len(ready) >= 1, 10.0)
        status = ReadyStatus.from_json(ready[0].data)
        assert status.node == '/multi_view_node'
        assert {'/camera/rgb/image_color', '/camera/pose', '/camera/rgb/camera_info'} <= set(
            status.subscribes
        )

        stamps = [m.sec_to_ns(s) for s in seq.stamps[:5]]
        for i, stamp in enumerate(stamps):  # images first, no camera_info yet
            header = m.header_msg(stamp, FRAME, kind=m.RCLPY)
            image_pub.publish(m.rgb_image_msg(seq.frames[i].rgb, header, kind=m.RCLPY))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('image', 0) == 5, 10.0)
        # The callback counts an image before it holds it: the fifth may still be on its way in.
        assert ros.wait_for(lambda: len(node.awaiting_info) == 5, 10.0), len(node.awaiting_info)
        header = m.header_msg(stamps[0], FRAME, kind=m.RCLPY)
        info_pub.publish(m.camera_info_msg(seq.camera, header, kind=m.RCLPY))
        for i, stamp in enumerate(stamps):
            pose_pub.publish(
                m.pose_stamped_msg(seq.poses[i], m.header_msg(stamp, 'world', kind=m.RCLPY), kind=m.RCLPY)
            )
        assert ros.wait_for(lambda: node.posed_count == 5, 10.0), node.stats.snapshot().summary()
        assert node.wait_idle(30.0)
        assert ros.wait_for(lambda: sum(e.frame_id == 'image' for e in events) == 5, 10.0)
        snap = node.stats.snapshot()
    assert 'no_camera_info' not in snap.dropped
    acked = [m.stamp_to_ns(e.stamp) for e in events if e.frame_id == 'image']
    assert acked == stamps  # every image handled, in order
    chosen = [m.stamp_to_ns(e.stamp) for e in events if e.frame_id == 'chosen']
    assert chosen == stamps[2::2]  # every 2nd posed frame, but the first (no neighbour)


def test_every_image_is_seen_handled_and_done_once_in_that_order(synthetic_sequence):
    """What a paced replay follows: ``image_waiting`` for an image whose pose is not there yet,
    then one ``image`` (handled) and one ``image_done`` (the filter has updated with it) per
    image, in that order, also when the poses lag the images."""
    seq = synthetic_sequence
    with RosHarness() as ros:
        node = _mv_node(ros, keyframe_every=2)
        events = _events(ros)
        image_pub, info_pub, pose_pub = _publishers(ros)
        stamps = [m.sec_to_ns(s) for s in seq.stamps[:6]]
        info = m.camera_info_msg(seq.camera, m.header_msg(stamps[0], FRAME, kind=m.RCLPY), kind=m.RCLPY)
        info_pub.publish(info)

        def pose(i: int) -> None:
            header = m.header_msg(stamps[i], 'world', kind=m.RCLPY)
            pose_pub.publish(m.pose_stamped_msg(seq.poses[i], header, kind=m.RCLPY))

        def image(i: int) -> None:
            header = m.header_msg(stamps[i], FRAME, kind=m.RCLPY)
            image_pub.publish(m.rgb_image_msg(seq.frames[i].rgb, header, kind=m.RCLPY))

        for i in range(3):  # the images first: they wait for their poses
            image(i)
        assert ros.wait_for(lambda: sum(e.frame_id == 'image_waiting' for e in events) == 3, 10.0)
        for i in range(3):
            pose(i)
        for i in range(3, 6):  # then poses ahead of their images
            pose(i)
            # Two topics keep no order between them: the image goes once the node has its pose.
            assert ros.wait_for(lambda i=i: node.stats.snapshot().received.get('pose', 0) == i + 1, 10.0)
            image(i)
        assert ros.wait_for(lambda: sum(e.frame_id == 'image_done' for e in events) == 6, 30.0)
        assert node.wait_idle(30.0)
        time.sleep(0.2)
    kinds = [(m.stamp_to_ns(e.stamp), e.frame_id) for e in events if e.frame_id.startswith('image')]
    for i, stamp in enumerate(stamps):
        mine = [kind for s, kind in kinds if s == stamp]
        waited = ['image_waiting'] if i < 3 else []
        assert mine == [*waited, 'image', 'image_done'], (i, mine)


def test_keyframes_dropped_before_announcement_are_announced_as_dropped(synthetic_sequence):
    seq = synthetic_sequence
    n = 12
    with RosHarness() as ros:
        node = _mv_node(
            ros, keyframe_every=1, queue_size=1, queue_policy='latest', qos_depth=100, width=320, height=240
        )
        events = _events(ros)
        keyframes = ros.collect(Image, '/depth_fusion/keyframe/image')
        image_pub, info_pub, pose_pub = _publishers(ros)
        stamps = [m.sec_to_ns(s) for s in seq.stamps[:n]]
        for i, stamp in enumerate(stamps):  # a burst: far faster than the plane sweep
            header = m.header_msg(stamp, FRAME, kind=m.RCLPY)
            pose_pub.publish(
                m.pose_stamped_msg(seq.poses[i], m.header_msg(stamp, 'world', kind=m.RCLPY), kind=m.RCLPY)
            )
            info_pub.publish(m.camera_info_msg(seq.camera, header, kind=m.RCLPY))
            image_pub.publish(m.rgb_image_msg(seq.frames[i].rgb, header, kind=m.RCLPY))
        assert ros.wait_for(lambda: sum(e.frame_id == 'image' for e in events) == n, 20.0)
        assert node.wait_idle(60.0)
        time.sleep(0.3)
        snap = node.stats.snapshot()
        chosen = [m.stamp_to_ns(e.stamp) for e in events if e.frame_id == 'chosen']
        dropped = [
            m.stamp_to_ns(e.stamp) for e in events if e.frame_id == 'dropped:multi_view.worker_queue_full'
        ]
        announced = [m.stamp_to_ns(k.header.stamp) for k in keyframes]
    assert len(chosen) == node.keyframes_decided == n - 1
    assert len(dropped) == snap.dropped.get('worker_queue_full', 0) > 0
    assert sorted(announced + dropped) == chosen  # every chosen keyframe: announced or dropped
    assert np.all(np.diff(chosen) > 0)


def test_run_cli_is_paced_unless_realtime(tmp_path):
    """``depth-fusion run`` is paced by default; ``--realtime`` reaches the runner, and the
    replayer and node settings follow (what the user set wins)."""
    import argparse

    from depth_fusion_ros.cli import run as run_cli
    from depth_fusion_ros.nodes.graph.pacing import paced_overrides

    parser = argparse.ArgumentParser()
    run_cli.register(parser.add_subparsers())
    paced = run_cli.options_from_args(parser.parse_args(['run', '--bag', 'x.bag']))
    live = run_cli.options_from_args(
        parser.parse_args(
            ['run', '--bag', 'x.bag', '--realtime', '--set', 'fusion_node.queue_policy=drop_new']
        )
    )
    assert not paced.realtime and live.realtime
    p = paced_overrides(paced, {})
    assert p['bag_replayer']['pace'] is True and p['bag_replayer']['wait_for_nodes'] == ['']
    assert p['bag_replayer']['wait_ready'] == ['single_view_node', 'multi_view_node', 'fusion_node']
    assert {p[n]['queue_policy'] for n in ('single_view_node', 'multi_view_node', 'fusion_node')} == {'block'}
    r = paced_overrides(live, {'fusion_node': {'queue_policy': 'drop_new'}})
    assert r['bag_replayer']['pace'] is False and r['fusion_node']['queue_policy'] == 'drop_new'
    assert 'queue_policy' not in r.get('multi_view_node', {})
    # a paced replay fuses every keyframe with all its points; a live one may shed them
    assert p['fusion_node']['load_max_points'] == 0
    assert 'load_max_points' not in r.get('fusion_node', {})
    # the replayer's own default (one keyframe in flight) unless the runner is told otherwise
    assert 'max_keyframes_in_flight' not in p['bag_replayer']
    from depth_fusion_ros.nodes.bag_replayer import REPLAYER_PARAMS

    assert {s.name: s.default for s in REPLAYER_PARAMS}['max_keyframes_in_flight'] == 1


def test_the_live_count_says_how_many_images_came_or_that_none_did():
    """A launch whose camera topic is wrong ends with "0 keyframes chosen": the line says that
    no image reached the graph, and otherwise how many did."""
    from depth_fusion_ros.nodes.graph.summary import live_summary

    ledger = KeyframeLedger()
    assert live_summary(ledger.snapshot(), 3.0).endswith(
        '0 keyframes chosen, 0 fused, 0 dropped in 3.0 s (live); no image reached multi_view_node '
        '(check --image and that the camera publishes)'
    )
    for stamp in range(1, 13):
        ledger.add(stamp, 'image')
    ledger.add(5, 'chosen')
    ledger.add(5, 'fused')
    line = live_summary(ledger.snapshot(), 2.0)
    assert line == '1 keyframes chosen, 1 fused, 0 dropped in 2.0 s (live); 12 images reached multi_view_node'


def test_a_launch_that_fused_nothing_says_why():
    """`depth-fusion launch` stopped by Ctrl-C exited 0 after "0 keyframes chosen, 0 fused" (a
    wrong camera topic, a SLAM that never published): the reason it now exits 1 with."""
    from depth_fusion_ros.nodes.graph.summary import live_empty

    ledger = KeyframeLedger()
    assert live_empty(ledger.snapshot()) == 'nothing was fused: no image reached multi_view_node'
    for stamp in range(1, 13):
        ledger.add(stamp, 'image')
    assert 'no keyframe was chosen from the 12 images' in live_empty(ledger.snapshot())
    ledger.add(5, 'chosen')
    ledger.add(5, 'dropped:fusion.unpaired')
    assert (
        live_empty(ledger.snapshot())
        == 'nothing was fused: none of the 1 keyframes chosen (see the drops above)'
    )
    ledger.add(10, 'chosen')
    ledger.add(10, 'fused')
    assert live_empty(ledger.snapshot()) is None


def test_a_run_that_fused_nothing_says_why_and_fails():
    """`depth-fusion run` on a bag too short for a keyframe ended "0 keyframes chosen, 0 fused"
    with exit 0; a script's `run && evaluate` went on with an empty recording."""
    from depth_fusion_ros.nodes.graph.summary import empty_run

    def result(chosen: list[int], fused: list[int], images: int) -> RunResult:
        return RunResult(
            announced=fused, fused=fused, missing={}, recorded=None, counts={}, seconds=1.0,
            chosen=chosen, drops={s: 'fusion.unpaired' for s in chosen if s not in fused}, paced=True,
            images_handled=images,
        )  # fmt: skip

    assert empty_run(result([], [], 3)) == (
        'no keyframe was chosen from the 3 images multi_view_node handled (too few posed frames, or '
        'too little motion between them): nothing was fused'
    )
    assert (
        empty_run(result([5, 10], [], 12)) == 'none of the 2 keyframes chosen was fused (see the drops above)'
    )
    assert empty_run(result([5, 10], [10], 12)) is None
