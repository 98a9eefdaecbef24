"""single_view_node over real DDS: the network's depth with the source header, bad inputs survived."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import save_torchscript_depth_model
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.qos import latched_qos
from depth_fusion_ros.nodes.single_view_node import SingleViewNode
from depth_fusion_ros.nodes.testing import RosHarness

K = m.RCLPY


class _BrightnessDepth(torch.nn.Module):
    """A stand-in network whose output depends on every pixel: 1 m + the mean normalised channel."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 1.0 + x.mean(dim=1, keepdim=True).abs()


@pytest.fixture(scope='module')
def torchscript_model(tmp_path_factory) -> Path:
    return save_torchscript_depth_model(_BrightnessDepth(), tmp_path_factory.mktemp('model'), 'brightness')


def _rgb(seed: int, height: int = 240, width: int = 320) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def _image(rgb: np.ndarray, stamp_ns: int, encoding: str = 'rgb8') -> Image:
    msg = m.image_msg(rgb, 'rgb8', m.header_msg(stamp_ns, 'camera_rgb_optical_frame', kind=K), kind=K)
    msg.encoding = encoding
    return msg


def test_keyframe_depth_has_source_header_and_bad_inputs_are_dropped(torchscript_model):
    from depth_fusion_ros.singleview.predictor import load_predictor

    reference = load_predictor(torchscript_model)
    with RosHarness() as ros:
        node = ros.add(
            SingleViewNode(
                context=ros.context,
                parameter_overrides=[
                    Parameter('model', value=str(torchscript_model)),
                    Parameter('queue_size', value=8),
                ],
            )
        )
        images = ros.publisher(Image, '/depth_fusion/keyframe/image')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([images])
        good = {1_000_000_000 + i * 100_000_000: _rgb(i) for i in range(3)}
        stamps = sorted(good)
        images.publish(_image(good[stamps[0]], stamps[0]))
        images.publish(_image(good[stamps[0]], stamps[0]))  # duplicate stamp
        images.publish(_image(good[stamps[0]], stamps[0] - 1))  # older than the previous one
        images.publish(_image(good[stamps[1]], stamps[1], encoding='yuv420'))  # unsupported encoding
        truncated = _image(good[stamps[1]], stamps[1])
        truncated.data = truncated.data[:-10]
        images.publish(truncated)  # data shorter than step * height
        images.publish(_image(good[stamps[1]], stamps[1]))
        images.publish(_image(good[stamps[2]], stamps[2]))
        assert ros.wait_for(lambda: len(depths) >= 3, timeout=20.0), node.stats.snapshot().summary()
        snap = node.stats.snapshot()

    assert [m.stamp_to_ns(d.header.stamp) for d in depths] == stamps
    assert snap.dropped == {
        'duplicate_stamp_image': 1,
        'stamp_out_of_order_image': 1,
        'bad_encoding': 1,
        'bad_image': 1,
    }
    for msg in depths:
        assert msg.encoding == '32FC1' and msg.header.frame_id == 'camera_rgb_optical_frame'
        assert (msg.width, msg.height) == (320, 240)
        expected = reference.predict(good[m.stamp_to_ns(msg.header.stamp)])
        np.testing.assert_allclose(m.image_to_numpy(msg), expected, rtol=1e-5)


def test_keyframes_sent_while_the_network_loads_are_processed_after(torchscript_model):
    """A live stream that begins while the node still loads its network loses no keyframe:
    the node subscribes first, DDS keeps what comes, the loaded network processes it."""
    sent = threading.Event()

    class _SlowLoad(SingleViewNode):
        def _load_predictor(self, spec, device):
            assert sent.wait(20.0), 'the keyframes were never sent'
            return super()._load_predictor(spec, device)

    with RosHarness() as ros:
        images = ros.publisher(Image, '/depth_fusion/keyframe/image')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        stamps = [2_000_000_000 + i * 200_000_000 for i in range(3)]

        def stream() -> None:
            if ros.wait_for_subscribers([images], timeout=20.0):
                for i, stamp in enumerate(stamps):
                    images.publish(_image(_rgb(i), stamp))
                    time.sleep(0.1)
                time.sleep(0.3)  # delivered to the subscription's history
            sent.set()

        sender = threading.Thread(target=stream, daemon=True)
        sender.start()
        node = ros.add(
            _SlowLoad(
                context=ros.context, parameter_overrides=[Parameter('model', value=str(torchscript_model))]
            )
        )
        sender.join(5.0)
        assert ros.wait_for(lambda: len(depths) >= 3, timeout=20.0), node.stats.snapshot().summary()
        snap = node.stats.snapshot()
    assert [m.stamp_to_ns(d.header.stamp) for d in depths] == stamps
    assert snap.dropped == {}


#: A raw camera's topics, remapped onto the node's inputs (``input_rectified: false``).
RAW_REMAPS = [
    '--ros-args',
    '-r',
    'depth_fusion/keyframe/image:=/cam/image',
    '-r',
    'depth_fusion/keyframe/camera_info:=/cam/info',
]


def _raw_camera_node(ros: RosHarness, model: Path, **params: object) -> SingleViewNode:
    """A single_view_node reading the raw camera on ``/cam/image`` and ``/cam/info``."""
    overrides = [Parameter('model', value=str(model)), Parameter('input_rectified', value=False)]
    overrides += [Parameter(name, value=value) for name, value in params.items()]
    return ros.add(SingleViewNode(context=ros.context, parameter_overrides=overrides, cli_args=RAW_REMAPS))


def test_raw_camera_input_is_undistorted_and_output_kind_is_latched(torchscript_model):
    camera = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    with RosHarness() as ros:
        # camera_info_wait 0: the first image, before camera_info, dropped at once
        node = _raw_camera_node(ros, torchscript_model, queue_size=8, camera_info_wait=0.0)
        images = ros.publisher(Image, '/cam/image')
        infos = ros.publisher(CameraInfo, '/cam/info')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([images, infos])
        images.publish(_image(_rgb(0, 480, 640), 10))  # no camera_info yet: dropped
        ros.wait_for(lambda: node.stats.snapshot().dropped.get('no_camera_info') == 1, 5.0)
        infos.publish(
            m.camera_info_msg(camera, m.header_msg(20, 'cam', kind=K), kind=K, D=(0.1, -0.05, 0, 0, 0))
        )
        ros.wait_for(lambda: node.stats.snapshot().received.get('camera_info') == 1, 5.0)
        images.publish(_image(_rgb(1, 240, 320), 30))  # 320x240 but camera_info says 640x480
        images.publish(_image(_rgb(2, 480, 640), 40))
        assert ros.wait_for(lambda: len(depths) >= 1, timeout=20.0), node.stats.snapshot().summary()
        # joins late: the latched sample, and the value published again on the match (announce.py)
        kinds = ros.collect(String, '/depth_fusion/single_view/output_kind', latched_qos())
        assert ros.wait_for(lambda: len(kinds) >= 1, timeout=30.0)  # discovery of a late joiner under load
        snap = node.stats.snapshot()
    assert snap.dropped == {'no_camera_info': 1, 'size_mismatch': 1}
    assert (depths[0].width, depths[0].height) == (320, 240) and m.stamp_to_ns(depths[0].header.stamp) == 40
    assert len(kinds) <= 2 and {k.data for k in kinds} == {'metric_depth'}


def test_raw_camera_images_before_the_first_camera_info_wait_for_it(torchscript_model):
    """A raw camera whose camera_info comes a moment after its first images: they wait
    (``camera_info_wait``) and are processed in order once it comes; an image further back than
    the wait is dropped as ``no_camera_info``, counted."""
    camera = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    with RosHarness() as ros:
        node = _raw_camera_node(ros, torchscript_model, camera_info_wait=0.5)
        images = ros.publisher(Image, '/cam/image', latched_qos(10))
        infos = ros.publisher(CameraInfo, '/cam/info')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([images, infos])
        stamps = [0, 400_000_000, 700_000_000, 800_000_000]  # the first is 0.8 s behind the last
        for stamp in stamps:
            images.publish(_image(_rgb(stamp % 7), stamp))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('image') == 4, 5.0)
        time.sleep(0.2)
        assert not depths and node.stats.snapshot().dropped == {'no_camera_info': 1}
        infos.publish(m.camera_info_msg(camera, m.header_msg(stamps[-1], 'cam', kind=K), kind=K))
        assert ros.wait_for(lambda: len(depths) >= 3, timeout=20.0), node.stats.snapshot().summary()
        snap = node.stats.snapshot()
    assert [m.stamp_to_ns(d.header.stamp) for d in depths] == stamps[1:]
    assert snap.dropped == {'no_camera_info': 1} and snap.received['image'] == 4, snap.summary()


def test_raw_camera_input_takes_the_lens_the_multi_view_node_took(torchscript_model):
    """Reading the raw camera itself, the node undistorts with the lens ``multi_view_node``
    took (``depth_fusion/calibration/camera_info``, latched: published before the node
    started) from the image stamped with it on, and the depth before it is of the told
    calibration's image; a calibration that differs by more than ``k1`` is said, not taken."""
    from depth_fusion_ros.data.undistort import CameraCalibration
    from depth_fusion_ros.nodes.image_input import CameraInput
    from depth_fusion_ros.nodes.lens_topic import TOPIC_LENS_CAMERA_INFO, lens_info_msg, lens_qos
    from depth_fusion_ros.singleview.predictor import load_predictor

    camera = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    told = m.camera_info_msg(camera, m.header_msg(20, 'cam', kind=K), kind=K)
    sent = {stamp: _image(_rgb(stamp), stamp) for stamp in (40, 50, 80)}
    with RosHarness() as ros:
        lens = ros.publisher(CameraInfo, '/' + TOPIC_LENS_CAMERA_INFO, lens_qos())
        lens.publish(lens_info_msg(CameraCalibration(camera, 'plumb_bob', (-0.09, 0, 0, 0, 0)), 50, 'cam'))
        node = _raw_camera_node(ros, torchscript_model)
        images = ros.publisher(Image, '/cam/image')
        infos = ros.publisher(CameraInfo, '/cam/info')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([images, infos])
        infos.publish(told)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('camera_info') == 1, 5.0)
        assert ros.wait_for(lambda: node.lens._pending, 10.0)  # the latched calibration
        images.publish(sent[40])
        assert ros.wait_for(lambda: len(depths) >= 1, timeout=20.0), node.stats.snapshot().summary()
        before = node.camera_input.lens_k1
        images.publish(sent[50])
        assert ros.wait_for(lambda: len(depths) >= 2, timeout=20.0), node.stats.snapshot().summary()
        other = CameraCalibration(camera, 'plumb_bob', (-0.05, 0.2, 0, 0, 0))  # another k2
        lens.publish(lens_info_msg(other, 70, 'cam'))
        assert ros.wait_for(lambda: node.lens._pending, 10.0)
        images.publish(sent[80])
        assert ros.wait_for(lambda: len(depths) >= 3, timeout=20.0), node.stats.snapshot().summary()
        snap = node.stats.snapshot()
    assert before == 0.0 and node.camera_input.lens_k1 == pytest.approx(-0.09)
    assert snap.noted == {'lens_followed': 1, 'lens_not_followed': 1} and snap.dropped == {}, snap.summary()
    reference, own = load_predictor(torchscript_model), CameraInput(320, 240)
    own.update(told)
    for depth, k1 in zip(depths, (0.0, -0.09, -0.09), strict=True):
        stamp = m.stamp_to_ns(depth.header.stamp)
        own.lens_k1 = k1
        expected = reference.predict(own.working_image(sent[stamp]).rgb)
        np.testing.assert_allclose(m.image_to_depth(depth), expected, rtol=1e-6, err_msg=str(stamp))
    assert [m.stamp_to_ns(d.header.stamp) for d in depths] == [40, 50, 80]


def test_missing_model_fails_at_start_naming_the_file(tmp_path):
    with RosHarness() as ros, pytest.raises(FileNotFoundError, match=r'nowhere\.pt'):
        SingleViewNode(
            context=ros.context, parameter_overrides=[Parameter('model', value=str(tmp_path / 'nowhere.pt'))]
        )


def test_input_qos_parameter_matches_a_best_effort_camera(torchscript_model):
    from depth_fusion_ros.nodes.qos import qos_profile

    with RosHarness() as ros:
        best_effort = ros.publisher(Image, '/depth_fusion/keyframe/image', qos_profile('sensor_data', 5))
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        ros.add(SingleViewNode('sv_reliable', context=ros.context, parameter_overrides=[
            Parameter('model', value=str(torchscript_model))]))  # fmt: skip
        node = ros.add(
            SingleViewNode(
                'sv_sensor_data',
                context=ros.context,
                parameter_overrides=[
                    Parameter('model', value=str(torchscript_model)),
                    Parameter('input_qos', value='sensor_data'),
                ],
            )
        )
        # a reliable subscription does not match a best-effort publisher: only one match
        assert ros.wait_for(lambda: best_effort.get_subscription_count() == 1, 10.0)
        time.sleep(0.3)
        assert best_effort.get_subscription_count() == 1
        best_effort.publish(_image(_rgb(5), 50))
        assert ros.wait_for(lambda: len(depths) == 1, 20.0)
    assert node.stats.snapshot().processed == 1 and m.stamp_to_ns(depths[0].header.stamp) == 50


def test_an_unexpected_error_in_a_callback_does_not_end_the_node(torchscript_model):
    with RosHarness() as ros:
        node = ros.add(SingleViewNode(context=ros.context, parameter_overrides=[
            Parameter('model', value=str(torchscript_model))]))  # fmt: skip
        images = ros.publisher(Image, '/depth_fusion/keyframe/image')
        depths = ros.collect(Image, '/depth_fusion/single_view/depth')
        assert ros.wait_for_subscribers([images])
        real = node.camera_input.working_image
        calls = []

        def broken_once(msg):
            calls.append(msg)
            if len(calls) == 1:
                raise RuntimeError('a bug nobody anticipated')
            return real(msg)

        node.camera_input.working_image = broken_once
        images.publish(_image(_rgb(0), 10))
        assert ros.wait_for(lambda: node.stats.snapshot().dropped.get('callback_error') == 1, 10.0)
        images.publish(_image(_rgb(1), 20))
        assert ros.wait_for(lambda: len(depths) == 1, 20.0)
    assert m.stamp_to_ns(depths[0].header.stamp) == 20
