"""multi_view_node with multi_view.method=filter (the default) over real DDS: every posed frame
feeds the filter."""

from __future__ import annotations

import time

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from test_nodes_multi_view import _Camera, _mv_node, _stamps

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.nodes.multi_view_node import MultiViewNode
from depth_fusion_ros.nodes.qos import latched_qos
from depth_fusion_ros.nodes.testing import RosHarness

pytestmark = pytest.mark.usefixtures('one_torch_thread')

#: Keyframes every 6th frame, and every frame to the filter, as a paced replay.
EVERY_FRAME = {
    'keyframe_every': 6,
    'queue_size': 8,
    'qos_depth': 100,
    'filter.max_lag_frames': 0,
    'filter.max_update_rate': 0.0,
}


def test_default_filter_method_publishes_accurate_keyframe_depth(synthetic_sequence):
    """No ``multi_view.method`` given: the node runs the filter and announces it."""
    seq = synthetic_sequence
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    with RosHarness() as ros:
        node = _mv_node(ros, **EVERY_FRAME)
        assert node.params['multi_view.method'] == 'filter' and node.filter_feed is not None
        depth_msgs = ros.collect(Image, '/depth_fusion/multi_view/depth')
        score_msgs = ros.collect(Image, '/depth_fusion/multi_view/score')
        std_msgs = ros.collect(Image, '/depth_fusion/multi_view/depth_std')
        bias_msgs = ros.collect(Image, '/depth_fusion/multi_view/bias_std')
        ros.collect(CameraInfo, '/depth_fusion/keyframe/camera_info')
        # latched: a fusion_node that starts later still learns the method (its stage-1 rule)
        methods = ros.collect(String, '/depth_fusion/multi_view/method', latched_qos())
        cam = _Camera(ros)
        for i, frame in enumerate(seq.frames):
            cam.publish_pose(frame.pose, stamps[i])
            cam.publish_image(frame.rgb, stamps[i], seq.camera)
            time.sleep(0.02)
        expected_keys = [6, 12, 18]
        assert ros.wait_for(lambda: len(score_msgs) == len(expected_keys), 120.0), (
            node.stats.snapshot().summary()
        )
        assert ros.wait_for(lambda: node.filter_feed.fed == len(seq.frames), 30.0)
        snap = node.stats.snapshot()
        filt = node.filter_feed.filter
        extra = node.diagnostic_extra()

    assert snap.dropped == {}, snap.summary()
    # Each frame's pose was refined against its filter keyframe's image (filter.refine_poses, on by
    # default), and the diagnostics count it.
    refined = extra['filter frames with a refined pose (filter.refine_poses)']
    kept = extra['filter frames that kept their told pose (refinement failed)']
    assert refined == filt.stats.refined >= 0.8 * (len(seq.frames) - 1)
    assert kept == filt.stats.kept_told and refined + kept <= len(seq.frames) - 1
    assert {msg.data for msg in methods} == {'filter'} and len(methods) <= 2  # announce.py
    assert _stamps(depth_msgs) == [stamps[k] for k in expected_keys]
    # The filter saw every posed frame as it came, not only the keyframes (nor only up to the last).
    assert isinstance(filt, DepthFilter) and filt.stats.frames == len(seq.frames)
    assert _stamps(std_msgs) == _stamps(depth_msgs)  # the guard's parallax evidence, per keyframe
    assert _stamps(bias_msgs) == _stamps(depth_msgs)  # the part of it every estimate shares
    for depth_msg, std_msg, bias_msg in zip(depth_msgs, std_msgs, bias_msgs, strict=True):
        depth, std = m.image_to_numpy(depth_msg), m.image_to_numpy(std_msg)
        assert np.array_equal(np.isfinite(std), np.isfinite(depth)) and np.nanmin(std) > 0
        bias = m.image_to_numpy(bias_msg)  # the filter's focal bias: within the std, never above it
        assert np.array_equal(np.isfinite(bias), np.isfinite(depth))
        assert np.nanmin(bias) >= 0 and np.all(bias[np.isfinite(bias)] <= std[np.isfinite(bias)] * (1 + 1e-5))
    for k, depth_msg, score_msg in zip(expected_keys, depth_msgs, score_msgs, strict=True):
        depth, score = m.image_to_numpy(depth_msg), m.image_to_numpy(score_msg)
        gt = seq.frames[k].depth
        valid = np.isfinite(depth) & np.isfinite(gt)
        assert valid.mean() > 0.05, f'keyframe {k}: density {valid.mean():.3f}'
        assert np.array_equal(np.isfinite(score), np.isfinite(depth))
        assert np.median(np.abs(depth[valid] - gt[valid]) / gt[valid]) < 0.04


def test_unknown_method_is_refused():
    with RosHarness() as ros, pytest.raises(Exception, match=r'multi_view\.method'):
        MultiViewNode(
            context=ros.context, parameter_overrides=[Parameter('multi_view.method', value='magic')]
        )


@pytest.mark.parametrize('shift_s', [0.0, 30.0])
def test_a_sequence_played_again_starts_over_instead_of_being_dropped(synthetic_sequence, shift_s):
    """The same stamps again (a bag played twice, a client restarted), or later ones after a
    long gap (another sequence played after this one): the node takes it for a new stream,
    once, and its keyframes come out as the first time's, from a filter that started over."""
    seq = synthetic_sequence
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    second = [s + m.sec_to_ns(shift_s) for s in stamps]
    expected_keys = [6, 12, 18]
    with RosHarness() as ros:
        node = _mv_node(ros, stream_restart_jump=0.5, **EVERY_FRAME)  # the sequence lasts 0.8 s
        depth_msgs = ros.collect(Image, '/depth_fusion/multi_view/depth')
        cam = _Camera(ros)
        for n_pass, pass_stamps in ((1, stamps), (2, second)):
            for i, frame in enumerate(seq.frames):
                cam.publish_pose(frame.pose, pass_stamps[i])
                cam.publish_image(frame.rgb, pass_stamps[i], seq.camera)
                time.sleep(0.02)
            count = n_pass * len(expected_keys)
            assert ros.wait_for(lambda c=count: len(depth_msgs) == c, 120.0), node.stats.snapshot().summary()
        # every frame of both passes through the filter (the last images may still be on their
        # way to the feed when the last keyframe is out: idle() alone passed early under load)
        assert ros.wait_for(lambda: node.filter_feed.fed == 2 * len(seq.frames), 30.0), node.filter_feed.fed
        assert ros.wait_for(lambda: node.filter_feed.idle(), 30.0)
        snap = node.stats.snapshot()
        frames_seen = node.filter_feed.filter.stats.frames

    assert snap.dropped == {} and snap.noted.get('stream_restart') == 1, snap.summary()
    assert _stamps(depth_msgs) == [stamps[k] for k in expected_keys] + [second[k] for k in expected_keys]
    assert frames_seen == len(seq.frames)  # the filter of the second pass saw only its frames
    for k, depth_msg in zip(expected_keys * 2, depth_msgs, strict=True):
        depth, gt = m.image_to_numpy(depth_msg), seq.frames[k].depth
        valid = np.isfinite(depth) & np.isfinite(gt)
        assert valid.mean() > 0.05 and np.median(np.abs(depth[valid] - gt[valid]) / gt[valid]) < 0.04
