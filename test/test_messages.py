"""numpy <-> message conversions, for rclpy classes and rosbags dataclasses."""

from __future__ import annotations

import numpy as np
import pytest
from message_kinds import KIND_IDS, KINDS, TYPESTORE
from rosbags.typesys import Stores, get_typestore

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.undistort import CameraCalibration
from depth_fusion_ros.geometry import PoseError, make_pose

ROS1_TYPESTORE = get_typestore(Stores.ROS1_NOETIC)
STAMP_NS = 1_305_031_102_175_304_123


def _sample(encoding: str, rng: np.random.Generator, h: int = 5, w: int = 7) -> np.ndarray:
    dtype, channels = m.ENCODINGS[encoding]
    shape = (h, w) if channels == 1 else (h, w, channels)
    if dtype == np.float32:
        arr = rng.uniform(0.1, 10.0, shape).astype(np.float32)
        arr[0, 0] = np.nan
        return arr
    return rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)


def _header(kind):
    return m.header_msg(STAMP_NS, 'cam', kind=kind)


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize('encoding', list(m.ENCODINGS))
def test_image_round_trip_every_encoding(kind, encoding):
    arr = _sample(encoding, np.random.default_rng(0))
    msg = m.image_msg(arr, encoding, _header(kind), kind=kind)
    assert msg.encoding == encoding and msg.width == 7 and msg.height == 5
    np.testing.assert_array_equal(m.image_to_numpy(msg), arr)
    assert m.stamp_to_ns(msg.header.stamp) == STAMP_NS and msg.header.frame_id == 'cam'


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize('encoding', ['16UC1', 'mono16', '32FC1'])
def test_big_endian_round_trip(kind, encoding):
    arr = _sample(encoding, np.random.default_rng(1))
    msg = m.image_msg(arr, encoding, _header(kind), kind=kind, bigendian=True)
    assert msg.is_bigendian
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    # the wire really is big-endian: the first pixel's bytes are reversed vs little-endian
    little = np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder('<')).tobytes()
    assert raw[: arr.dtype.itemsize].tobytes() == little[: arr.dtype.itemsize][::-1]
    out = m.image_to_numpy(msg)
    assert out.dtype.isnative
    np.testing.assert_array_equal(out, arr)


def _pad_rows(msg, pad: int) -> None:
    """Rewrite ``msg`` with ``pad`` junk bytes at the end of every row."""
    rows = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(msg.height, msg.step)
    junk = np.full((msg.height, pad), 0xAB, dtype=np.uint8)
    padded = np.hstack((rows, junk))
    msg.step = msg.step + pad
    msg.data = padded.tobytes() if not isinstance(msg.data, np.ndarray) else padded.ravel()


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize(('encoding', 'bigendian'), [('rgb8', False), ('32FC1', False), ('16UC1', True)])
def test_row_padding_is_honoured(kind, encoding, bigendian):
    arr = _sample(encoding, np.random.default_rng(2))
    msg = m.image_msg(arr, encoding, _header(kind), kind=kind, bigendian=bigendian)
    _pad_rows(msg, 6)
    np.testing.assert_array_equal(m.image_to_numpy(msg), arr)


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_image_to_rgb_orders_channels(kind):
    rgb = _sample('rgb8', np.random.default_rng(3))
    hdr = _header(kind)
    bgr = rgb[..., ::-1]
    rgba = np.dstack((rgb, np.full(rgb.shape[:2], 7, np.uint8)))
    bgra = np.dstack((bgr, np.full(rgb.shape[:2], 7, np.uint8)))
    for arr, enc in [(rgb, 'rgb8'), (bgr, 'bgr8'), (rgba, 'rgba8'), (bgra, 'bgra8')]:
        out = m.image_to_rgb(m.image_msg(arr, enc, hdr, kind=kind))
        np.testing.assert_array_equal(out, rgb)
        assert out.flags.c_contiguous
    grey = rgb[..., 0]
    out = m.image_to_rgb(m.image_msg(grey, 'mono8', hdr, kind=kind))
    np.testing.assert_array_equal(out, np.dstack((grey, grey, grey)))


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_image_to_depth(kind):
    hdr = _header(kind)
    mm = np.array([[0, 1000], [2500, 65535]], dtype=np.uint16)
    depth = m.image_to_depth(m.image_msg(mm, '16UC1', hdr, kind=kind))
    np.testing.assert_allclose(depth, [[np.nan, 1.0], [2.5, 65.535]], rtol=1e-6)
    metres = np.array([[np.nan, 1.5], [np.inf, -1.0]], dtype=np.float32)
    depth = m.image_to_depth(m.depth_image_msg(metres, hdr, kind=kind))
    np.testing.assert_array_equal(np.isnan(depth), [[True, False], [True, True]])
    assert depth[0, 1] == np.float32(1.5)
    with pytest.raises(ValueError, match='32FC1 or 16UC1'):
        m.image_to_depth(m.image_msg(mm.astype(np.uint8), 'mono8', hdr, kind=kind))


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_bad_images_raise(kind):
    hdr = _header(kind)
    arr = np.zeros((4, 6, 3), np.uint8)
    with pytest.raises(ValueError, match="unsupported image encoding 'yuv420'"):
        m.image_msg(arr, 'yuv420', hdr, kind=kind)
    with pytest.raises(ValueError, match='dtype uint8'):
        m.image_msg(arr.astype(np.uint16), 'rgb8', hdr, kind=kind)
    with pytest.raises(ValueError, match='shape'):
        m.image_msg(arr, 'mono8', hdr, kind=kind)
    msg = m.image_msg(arr, 'rgb8', hdr, kind=kind)
    msg.encoding = 'yuv420'
    with pytest.raises(ValueError, match='unsupported image encoding'):
        m.image_to_numpy(msg)
    msg = m.image_msg(arr, 'rgb8', hdr, kind=kind)
    msg.step = 10
    with pytest.raises(ValueError, match='step 10 is smaller'):
        m.image_to_numpy(msg)
    msg = m.image_msg(arr, 'rgb8', hdr, kind=kind)
    msg.height = 5
    with pytest.raises(ValueError, match='expected step\\*height'):
        m.image_to_numpy(msg)
    with pytest.raises(ValueError, match='cannot make an RGB image'):
        m.image_to_rgb(m.image_msg(np.zeros((2, 2), np.float32), '32FC1', hdr, kind=kind))


def test_rclpy_and_rosbags_bytes_agree():
    pytest.importorskip('rclpy')
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image

    arr = _sample('rgb8', np.random.default_rng(4), 48, 64)
    bag_msg = m.image_msg(arr, 'rgb8', _header(TYPESTORE), kind=TYPESTORE)
    raw = TYPESTORE.serialize_cdr(bag_msg, 'sensor_msgs/msg/Image')
    ros_msg = deserialize_message(bytes(raw), Image)
    np.testing.assert_array_equal(m.image_to_rgb(ros_msg), arr)
    assert m.stamp_to_ns(ros_msg.header.stamp) == STAMP_NS
    rcl_msg = m.image_msg(arr, 'rgb8', _header(m.RCLPY), kind=m.RCLPY)
    # and the other way: rclpy's bytes decode with rosbags (padding bytes may differ, so
    # compare the decoded content, not the raw bytes)
    back = TYPESTORE.deserialize_cdr(serialize_message(rcl_msg), 'sensor_msgs/msg/Image')
    np.testing.assert_array_equal(m.image_to_rgb(back), arr)


def test_stamps_are_exact():
    assert m.sec_to_ns(1305031102.175304) == 1305031102175304000
    assert m.ns_to_sec(1305031102175304000) == 1305031102.175304
    for kind in KINDS:
        t = m.time_msg(STAMP_NS, kind=kind)
        assert (t.sec, t.nanosec) == (1305031102, 175304123)
        assert m.stamp_to_ns(t) == STAMP_NS
        assert m.stamp_to_sec(t) == pytest.approx(1305031102.175304123, abs=1e-6)
        hdr = m.header_msg(1305031102.175304, 'f', kind=kind)
        assert m.stamp_to_ns(hdr.stamp) == 1305031102175304000
        hdr2 = m.header_msg(hdr.stamp, 'g', kind=kind)
        assert m.stamp_to_ns(hdr2.stamp) == 1305031102175304000 and hdr2.frame_id == 'g'
    with pytest.raises(TypeError):
        m.time_msg(1.5, kind=TYPESTORE)
    with pytest.raises(ValueError, match='finite'):
        m.sec_to_ns(float('nan'))


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_camera_info_round_trip(kind):
    cam = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3)
    calib = CameraCalibration(cam, 'plumb_bob', (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
    msg = m.camera_info_msg(calib, _header(kind), kind=kind)
    back = m.camera_info_to_calibration(msg)
    assert back == calib
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], cam.K)
    plain = m.camera_info_to_calibration(m.camera_info_msg(cam.scaled(320, 240), _header(kind), kind=kind))
    assert plain.camera == cam.scaled(320, 240) and not plain.is_distorted
    uncalibrated = m.camera_info_msg(cam, _header(kind), kind=kind)
    uncalibrated.k = np.zeros(9)
    with pytest.raises(ValueError, match='not calibrated'):
        m.camera_info_to_calibration(uncalibrated)


def test_ros1_camera_info_is_read():
    cam = PinholeCamera(64, 48, 50.0, 51.0, 31.5, 23.5)
    msg = m.camera_info_msg(
        CameraCalibration(cam, 'plumb_bob', (0.1, 0, 0, 0, 0)), _header(ROS1_TYPESTORE), kind=ROS1_TYPESTORE
    )
    assert hasattr(msg, 'K') and msg.header.seq == 0
    assert m.camera_info_to_calibration(msg).camera == cam


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_pose_round_trip_and_validation(kind):
    T = make_pose([1.0, -2.0, 0.5], [0.1, -0.3, 0.2, 0.9])
    msg = m.pose_stamped_msg(T, m.header_msg(STAMP_NS, 'world', kind=kind), kind=kind)
    assert msg.header.frame_id == 'world'
    np.testing.assert_allclose(m.pose_stamped_to_matrix(msg), T, atol=1e-12)
    msg.pose.orientation.w = 2.0
    with pytest.raises(PoseError, match='not normalised'):
        m.pose_stamped_to_matrix(msg)
    msg.pose.orientation.w = float('nan')
    with pytest.raises(PoseError, match='non-finite'):
        m.pose_stamped_to_matrix(msg)
    msg = m.pose_stamped_msg(T, _header(kind), kind=kind)
    msg.pose.position.x = float('inf')
    with pytest.raises(PoseError, match='non-finite'):
        m.pose_stamped_to_matrix(msg)
    with pytest.raises(PoseError):
        m.pose_stamped_msg(np.full((4, 4), np.nan), _header(kind), kind=kind)


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_pointcloud2(kind):
    rng = np.random.default_rng(5)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    msg = m.pointcloud2_msg(xyz, _header(kind), kind=kind, rgb=rgb)
    assert msg.point_step == 16 and msg.width == 50 and msg.is_dense
    fields = m.pointcloud2_to_numpy(msg)
    np.testing.assert_array_equal(np.stack([fields['x'], fields['y'], fields['z']], axis=1), xyz)
    np.testing.assert_array_equal(fields['rgb'], rgb)
    assert m.pointcloud2_msg(xyz, _header(kind), kind=kind).point_step == 12


def test_pointcloud2_is_valid_cdr_for_rclpy():
    pytest.importorskip('rclpy')
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    msg = m.pointcloud2_msg(xyz, _header(TYPESTORE), kind=TYPESTORE, rgb=np.zeros((4, 3), np.uint8))
    ros = deserialize_message(bytes(TYPESTORE.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2')), PointCloud2)
    assert [f.name for f in ros.fields] == ['x', 'y', 'z', 'rgb']
    np.testing.assert_array_equal(m.pointcloud2_to_numpy(ros)['z'], xyz[:, 2])


def test_as_kind_rejects_junk():
    with pytest.raises(ValueError, match='kind must be'):
        m.as_kind(42)
    assert m.as_kind('rclpy') is m.RCLPY
