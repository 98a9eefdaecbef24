"""CompressedImage (image_transport 'compressed'): decode/encode, convert --compressed, reading
and replaying compressed bags, and choosing the transport from a bag's topics."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
from test_replayer import Listener, Spinning, context, make_replayer  # noqa: F401 (fixture)
from test_tum import make_tum_folder

from depth_fusion_ros.cli.main import main as cli_main
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.compressed import (
    ColourFormat,
    compressed_image_msg,
    decode_compressed,
    encode_compressed,
    image_transport_for_topics,
)
from depth_fusion_ros.data.rosbag_convert import tum_to_rosbag
from depth_fusion_ros.data.rosbag_read import bag_topics, load_bag_sequence
from depth_fusion_ros.data.tum import load_tum_sequence

RGB = '/camera/rgb/image_color'
COMPRESSED = RGB + '/compressed'


def _rgb(h: int = 24, w: int = 32) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_png_round_trip_is_exact_and_jpeg_is_close() -> None:
    rgb = _rgb()
    header = m.header_msg(5, 'cam', kind=m.RCLPY)
    png = compressed_image_msg(rgb, header, kind=m.RCLPY, fmt='png')
    assert png.format == 'rgb8; png compressed bgr8'
    np.testing.assert_array_equal(decode_compressed(png), rgb)
    smooth = np.repeat(np.linspace(0, 255, 32, dtype=np.uint8)[None, :, None], 24, 0).repeat(3, 2)
    jpeg = compressed_image_msg(smooth, header, kind=m.RCLPY, fmt='jpeg', jpeg_quality=95)
    assert np.abs(decode_compressed(jpeg).astype(int) - smooth).max() <= 8
    # old drivers write just 'jpeg'; grey images become three equal channels
    grey = SimpleNamespace(format='jpeg', data=encode_compressed(smooth, 'jpeg'))
    assert decode_compressed(grey).shape == (24, 32, 3)


def test_a_large_jpeg_camera_is_decoded_at_half_size_and_matches_the_full_decode() -> None:
    """A 1296x972 JPEG camera (over three times the 320x240 grid) is decoded at 648x486 by JPEG's
    reduced decoding and undistorted from there (docs/nodes.md, "Cameras larger than
    640x480"): the working image matches the full decode's within a grey level on average;
    a PNG of the same camera, and a JPEG of a 640x480 camera, take the full decode exactly."""
    from depth_fusion_ros.camera import PinholeCamera
    from depth_fusion_ros.data.undistort import CameraCalibration, Undistorter
    from depth_fusion_ros.nodes.image_input import CameraInput, decode_colour

    yy, xx = np.mgrid[0:972, 0:1296]
    smooth = np.dstack([(xx * 255 // 1295), (yy * 255 // 971), ((xx + yy) % 256)]).astype(np.uint8)
    header = m.header_msg(5, 'cam', kind=m.RCLPY)
    cases = [((1296, 972), 'jpeg', False), ((1296, 972), 'png', True), ((640, 480), 'jpeg', True)]
    for (w, h), fmt, exact in cases:
        image = np.ascontiguousarray(smooth[:h, :w])
        msg = compressed_image_msg(image, header, kind=m.RCLPY, fmt=fmt, jpeg_quality=95)
        tum = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3).scaled(w, h)
        calibration = CameraCalibration(tum, 'plumb_bob', (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
        camera = CameraInput(320, 240)
        camera.update(m.camera_info_msg(calibration, header, kind=m.RCLPY))
        got = camera.working_image(msg)
        undistorter = Undistorter.for_calibration(camera.calibration, 320, 240)
        full = undistorter.rgb(decode_colour(msg))
        assert got.rgb.shape == (240, 320, 3) and got.camera == undistorter.camera
        if exact:
            np.testing.assert_array_equal(got.rgb, full)
        else:
            assert undistorter.shrink == 2
            assert np.abs(got.rgb.astype(float) - full).mean() < 1.0


@pytest.mark.parametrize(
    ('fmt', 'data', 'match'),
    [
        ('jpeg', b'', 'no data'),
        ('jpeg', b'\xff\xd8 not really a jpeg', 'cannot decode'),
        ('16UC1; compressedDepth png', b'x', 'compressedDepth'),
        ('rgb8; tiff compressed bgr8', b'x', 'neither jpeg nor png'),
    ],
)
def test_undecodable_messages_raise_a_clear_error(fmt: str, data: bytes, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        decode_compressed(SimpleNamespace(format=fmt, data=data))


def test_transport_is_chosen_from_the_topics() -> None:
    assert image_transport_for_topics([RGB, '/camera/pose']) == 'raw'
    assert image_transport_for_topics([COMPRESSED, '/camera/pose']) == 'compressed'
    assert image_transport_for_topics([RGB, COMPRESSED]) == 'raw'  # raw wins: no loss, no decoding
    assert image_transport_for_topics(['/other']) == 'raw'
    assert image_transport_for_topics(['/cam/image/compressed'], '/cam/image') == 'compressed'
    with pytest.raises(ValueError, match='compression must be one of png, jpeg'):
        ColourFormat('webp')


@pytest.mark.parametrize('fmt', ['png', 'jpeg'])
def test_compressed_bag_is_written_and_read_back(tmp_path, fmt: str) -> None:
    src = tmp_path / 'tum'
    make_tum_folder(src, n=4)
    out = tmp_path / 'bag'
    tum_to_rosbag(src, out, show_progress=False, colour=ColourFormat(fmt))
    topics = bag_topics(out)
    assert RGB not in topics and topics[COMPRESSED] == ('sensor_msgs/msg/CompressedImage', 4)
    assert image_transport_for_topics(topics) == 'compressed'
    folder = load_tum_sequence(src, width=32, height=24)
    bag = load_bag_sequence(out, width=32, height=24)
    assert len(bag) == 4
    for a, b in zip(folder.frames, bag.frames, strict=True):
        if fmt == 'png':
            np.testing.assert_array_equal(a.rgb, b.rgb)  # lossless: the evaluation is unchanged
        else:
            assert np.abs(a.rgb.astype(int) - b.rgb).mean() < 20  # random noise is JPEG's worst case


def test_cli_convert_compressed_and_its_option_errors(tmp_path, capsys) -> None:
    src = tmp_path / 'tum'
    make_tum_folder(src, n=3)
    out = tmp_path / 'jpeg_bag'
    args = ['convert', str(src), str(out), '--no-progress', '--compressed', 'jpeg', '--jpeg-quality', '80']
    assert cli_main(args) == 0
    assert 'jpeg-compressed' in capsys.readouterr().out
    assert bag_topics(out)[COMPRESSED][1] == 3
    assert cli_main(['convert', str(src), str(tmp_path / 'png'), '--no-progress', '--compressed']) == 0
    assert bag_topics(tmp_path / 'png')[COMPRESSED][1] == 3  # bare --compressed: png
    assert cli_main(['convert', str(src), str(tmp_path / 'x'), '--jpeg-quality', '80']) == 1
    assert '--jpeg-quality only applies with --compressed jpeg' in capsys.readouterr().err
    bad = ['convert', str(src), str(tmp_path / 'y'), '--compressed', 'jpeg', '--jpeg-quality', '0']
    assert cli_main(bad) == 1
    assert '--jpeg-quality must be in [1, 100]' in capsys.readouterr().err


def test_replayer_plays_a_compressed_bag(context, tmp_path) -> None:  # noqa: F811
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import CompressedImage

    src = tmp_path / 'tum'
    truth = make_tum_folder(src, n=4)
    out = tmp_path / 'bag'
    tum_to_rosbag(src, out, show_progress=False, colour=ColourFormat('png'))
    listener = Listener(context, {COMPRESSED: CompressedImage, '/diagnostics': DiagnosticArray})
    replayer = make_replayer(context, out, wait_topics=[COMPRESSED], rate=4.0)

    def finished_status() -> list:
        return [
            s
            for _, a in list(listener.got['/diagnostics'])
            for s in a.status
            if s.name == 'depth_fusion/bag_replayer' and s.message == 'finished'
        ]

    with Spinning(context, listener.node, replayer):
        replayer.start()
        assert replayer.finished.wait(20.0)
        listener.settle()
        deadline = time.monotonic() + 5.0
        while not finished_status() and time.monotonic() < deadline:
            time.sleep(0.05)
    values = {kv.key: kv.value for kv in finished_status()[0].values}
    assert values[f'published {COMPRESSED}'] == '4' and finished_status()[0].level == b'\x00'
    got = [msg for _, msg in listener.got[COMPRESSED]]
    assert len(got) == 4 and replayer.error is None
    expected = [truth['truth'][k]['rgb'] for k in sorted(truth['truth'])]
    for msg, rgb in zip(got, expected, strict=True):
        np.testing.assert_array_equal(decode_compressed(msg), rgb)  # PNG: bit-exact after the replay


def test_ros1_bag_converts_to_compressed_png_exactly(tmp_path) -> None:
    from test_rosbag_convert import write_ros1_bag

    from depth_fusion_ros.data.rosbag_convert import recorded_to_rosbag2
    from depth_fusion_ros.data.rosbag_read import iter_messages

    src = tmp_path / 'tum.bag'
    truth = write_ros1_bag(src, n=3)
    out = tmp_path / 'ros2'
    result = recorded_to_rosbag2(src, out, show_progress=False, colour=ColourFormat('png'))
    assert result.messages[COMPRESSED] == 3 and RGB not in result.messages
    for _, bag_time, msg in iter_messages(out, [COMPRESSED]):
        np.testing.assert_array_equal(decode_compressed(msg), truth[bag_time]['rgb'])


def test_run_takes_the_transport_and_pose_type_from_the_bag(tmp_path) -> None:
    """``depth-fusion run`` on a compressed bag needs no flag; a params file still wins."""
    from depth_fusion_ros.nodes.graph import RunOptions
    from depth_fusion_ros.nodes.graph.param_merge import bag_topic_types, node_overrides

    src = tmp_path / 'tum'
    make_tum_folder(src, n=2)
    out = tmp_path / 'bag'
    tum_to_rosbag(src, out, show_progress=False, colour=ColourFormat('png'))
    mv = node_overrides(RunOptions(bag=out), bag_topic_types(out))['multi_view_node']
    assert mv['image_transport'] == 'compressed' and mv['pose_type'] == 'pose_stamped'
    params = tmp_path / 'params.yaml'
    params.write_text('multi_view_node:\n  ros__parameters:\n    image_transport: raw\n    pose_type: auto\n')
    mv = node_overrides(RunOptions(bag=out, params_file=params), bag_topic_types(out))['multi_view_node']
    assert 'image_transport' not in mv and 'pose_type' not in mv


def test_the_image_path_bench_times_raw_and_jpeg_images() -> None:
    """``depth-fusion bench --only image_input`` (quick): a figure per size and transport."""
    from depth_fusion_ros.bench import BenchOptions, image_input

    rows = image_input.run(BenchOptions(quick=True))
    names = [row.name for row in rows]
    assert names == [
        '640x480 bgr8: image -> working grid',
        '640x480 JPEG: image -> working grid',
        '1296x972 bgr8: image -> working grid',
        '1296x972 JPEG: image -> working grid',
    ]
    assert all(row.unit == 'ms' and 0 < row.value < 10_000 for row in rows)
