"""multi_view_node's focal length check over real DDS: a camera_info whose focal length is 10 %
long is found from the images and poses, said once, and (``focal_check.mode: correct``, the
default) the keyframes after it carry the corrected intrinsics downstream."""

from __future__ import annotations

import pytest
from sensor_msgs.msg import CameraInfo, Image
from test_nodes_multi_view import _Camera, _mv_node, _send_checked

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.nodes.testing import RosHarness

pytestmark = pytest.mark.usefixtures('one_torch_thread')


@pytest.mark.parametrize('mode', ['correct', 'warn'])
def test_a_wrong_focal_length_is_found_and_corrected_downstream(mode):
    seq = render_sequence(stress_config('wrong_focal', width=320, height=240, frames=40, seed=5))
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    with RosHarness() as ros:
        node = _mv_node(
            ros,
            keyframe_every=6,
            queue_size=8,
            qos_depth=100,
            **{
                'filter.max_lag_frames': 0,
                'filter.max_update_rate': 0.0,
                'focal_check.pairs': 12,
                'focal_check.mode': mode,
            },
        )
        infos = ros.collect(CameraInfo, '/depth_fusion/keyframe/camera_info')
        depths = ros.collect(Image, '/depth_fusion/multi_view/depth')
        cam = _Camera(ros)
        for i, frame in enumerate(seq.frames):
            if i == 30:  # the check's 12 pairs are in these 30 frames: let its thread finish
                done = ros.wait_for(lambda: node.focal_check.result is not None, 60.0)
                assert done, node.focal_check.status()
            _send_checked(ros, node, cam, (frame.pose, stamps[i]), (frame.rgb, stamps[i], seq.camera), i + 1)
        assert ros.wait_for(lambda: len(depths) == 6, 120.0), node.stats.snapshot().summary()
        snap = node.stats.snapshot()
        result = node.focal_check.result
        status = node.diagnostic_extra()['focal length check']

    assert result is not None and result.verdict == 'disagrees', node.focal_check.status()
    assert result.fx == pytest.approx(seq.gt_camera.fx, rel=0.03)
    assert snap.noted.get('focal_disagrees') == 1 and snap.dropped == {}, snap.summary()
    assert status.startswith('disagrees: fx 288.8 ->')
    told = pytest.approx(seq.camera.fx)
    fxs = [float(msg.k[0]) for msg in infos]
    assert fxs[0] == told  # the first keyframe comes before the check has its pairs
    if mode == 'correct':  # then every keyframe carries the focal length the images agree on
        assert fxs[-1] == pytest.approx(result.fx) and fxs[-1] == pytest.approx(seq.gt_camera.fx, rel=0.03)
        assert all(fx in (told, pytest.approx(result.fx)) for fx in fxs)
    else:
        assert all(fx == told for fx in fxs)
