"""multi_view_node takes a lens camera_info does not hold, over real DDS: the lens stress case
(a barrel lens of k1 -0.1, camera_info without it, the rotation sweep) is found by the focal
length check, said once, and (``focal_check.mode: correct``, the default) the images from then
on are undistorted with the fitted ``k1``: the keyframe images published after it are the
pinhole camera's, those before it the lens's, and the calibration taken is published once,
stamped with the image it was taken at."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, Image
from test_nodes_multi_view import _Camera, _notes_of, _send_checked, _stream_check_node, _wait_keyframes_out

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.nodes.lens_topic import TOPIC_LENS_CAMERA_INFO, lens_qos
from depth_fusion_ros.nodes.testing import RosHarness

pytestmark = pytest.mark.usefixtures('one_torch_thread')

#: Seed 5 at 240x180: the focal check's early look (focal_check.lens_early_pairs 8) names the lens
#: (k1 about -0.105) at frame 33, before the mount check has its pairs.
SIZE = {'width': 240, 'height': 180, 'frames': 100, 'seed': 5}
PAIRS = 10


def _apart(a: np.ndarray, b: np.ndarray) -> float:
    inner = (slice(10, -10), slice(10, -10))
    return float(np.abs(a.astype(float) - b.astype(float))[inner].mean())


def test_a_lens_is_found_and_the_images_undistorted_from_then_on():
    lens = render_sequence(stress_config('lens_distortion', **SIZE))
    pinhole = render_sequence(stress_config('rotation', **SIZE))
    stamps = [m.sec_to_ns(s) for s in lens.stamps]
    with RosHarness() as ros:
        node = _stream_check_node(
            ros,
            SIZE,
            **{'focal_check.pairs': PAIRS, 'time_offset_check.mode': 'off'},
        )
        notes = _notes_of(node)
        keyframes = ros.collect(Image, '/depth_fusion/keyframe/image')
        depths = ros.collect(Image, '/depth_fusion/multi_view/depth')
        lens_infos = ros.collect(CameraInfo, '/' + TOPIC_LENS_CAMERA_INFO, lens_qos())
        cam = _Camera(ros)
        taken_at = None
        for i, frame in enumerate(lens.frames):
            _send_checked(ros, node, cam, (frame.pose, stamps[i]), (frame.rgb, stamps[i], lens.camera), i + 1)
            if taken_at is None and node.camera_input.lens_k1 != 0.0:
                taken_at = i
        _wait_keyframes_out(ros, node, depths, len(lens.frames))
        ros.wait_for(lambda: lens_infos, 5.0)
        snap = node.stats.snapshot()
        extra = node.diagnostic_extra()
        k1 = node.camera_input.lens_k1
    assert taken_at is not None and taken_at < 45, node.focal_check.status()  # 33: the early look
    assert -0.12 < k1 < -0.07
    assert extra['lens k1 added to the calibration (focal length check)'] == round(k1, 4)
    assert snap.noted.get('lens_corrected') == 1 and snap.dropped == {}, snap.summary()
    assert 'mount_disagrees' not in snap.noted, snap.summary()  # the lens is not read as a turn
    said = [message for reason, message in notes if reason == 'lens_corrected']
    assert 'k1 -0.' in said[0] and 'added to the calibration' in said[0] and 'start over' in said[0]
    index = {s: i for i, s in enumerate(stamps)}
    before, after = [], []
    for msg in keyframes:
        k = index[m.stamp_to_ns(msg.header.stamp)]
        rgb = m.image_to_rgb(msg)
        closer = _apart(rgb, pinhole.frames[k].rgb) < _apart(rgb, lens.frames[k].rgb)
        (after if k >= taken_at else before).append(closer)
    assert before and after, (taken_at, len(keyframes))
    assert not any(before) and all(after), (before, after)
    # The calibration taken, for a node that undistorts the raw camera itself (lens_topic.py).
    (info,) = lens_infos
    assert m.stamp_to_ns(info.header.stamp) == stamps[taken_at] and info.distortion_model == 'plumb_bob'
    np.testing.assert_allclose(info.d, (k1, 0, 0, 0, 0), atol=1e-12)
    assert (info.width, info.height, info.k[0]) == (lens.camera.width, lens.camera.height, lens.camera.fx)
