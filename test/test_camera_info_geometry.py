"""CameraInfo read as REP 104 / image_geometry define it: binning, ROI, and rectified images (P).

Pixel convention (``PinholeCamera``): ``(0, 0)`` is the centre of the top-left pixel. Binned
pixel ``j`` averages the ROI's full-sensor pixels ``j*b .. j*b + b - 1``, centred at
``x_offset + j*b + (b - 1) / 2``, so a full-sensor coordinate ``u`` is ``(u - x_offset + 0.5) / b - 0.5``
in the binned image and ``cx' = (cx - x_offset + 0.5) / b - 0.5``: image_geometry's
``(cx - x_offset) / b`` minus ``(b - 1) / (2 b)`` (0.25 px at b = 2). The undistortion test does
not tell the two apart (the Undistorter keeps K as the output camera, so cx only moves the
centre of the distortion; 0.25 px of it changes no grey level worth measuring); the projection
test does.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.camera_info_geometry import ImageWindow
from depth_fusion_ros.data.undistort import CameraCalibration, Undistorter
from depth_fusion_ros.nodes.image_input import CameraInput, InputError, working_grid_parameters

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ROS1_TYPESTORE = get_typestore(Stores.ROS1_NOETIC)
KINDS = [TYPESTORE, ROS1_TYPESTORE, m.RCLPY]
KIND_IDS = ['rosbags', 'rosbags-ros1', 'rclpy']

FULL = PinholeCamera(200, 160, 180.0, 182.0, 101.3, 78.6)
D = (-0.3, 0.1, 0.002, -0.0015, 0.0)
ROI = dict(x_offset=20, y_offset=16, width=160, height=128)
BIN = 2


def _info(kind, camera=FULL, D=D, *, binning=(0, 0), roi=None, P=None):
    """A CameraInfo of the full sensor ``camera`` with binning, ROI and P set as given."""
    msg = m.camera_info_msg(
        CameraCalibration(camera, 'plumb_bob', D), m.header_msg(1_000, 'cam', kind=kind), kind=kind
    )
    msg.binning_x, msg.binning_y = binning
    for name, value in (roi or {}).items():
        setattr(msg.roi, name, value)
    if P is not None:
        setattr(msg, 'p' if hasattr(msg, 'p') else 'P', np.asarray(P, dtype=np.float64).ravel())
    return msg


def _bin(img: np.ndarray, b: int = BIN) -> np.ndarray:
    """Hardware binning: the mean of each b x b block (rounded back to uint8)."""
    h, w = img.shape[:2]
    blocks = img.reshape(h // b, b, w // b, b, -1).astype(np.float64).mean(axis=(1, 3))
    return np.rint(blocks).astype(np.uint8).reshape(h // b, w // b, *img.shape[2:])


def _crop(img: np.ndarray) -> np.ndarray:
    x0, y0, w, h = ROI['x_offset'], ROI['y_offset'], ROI['width'], ROI['height']
    return img[y0 : y0 + h, x0 : x0 + w]


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_binning_and_roi_adjust_k_and_keep_d(kind):
    calib = m.camera_info_to_calibration(_info(kind, binning=(BIN, BIN), roi=ROI))
    cam = calib.camera
    x0, y0 = ROI['x_offset'], ROI['y_offset']
    assert (cam.width, cam.height) == (ROI['width'] // BIN, ROI['height'] // BIN) == (80, 64)
    assert cam.fx == FULL.fx / BIN and cam.fy == FULL.fy / BIN
    assert cam.cx == pytest.approx((FULL.cx - x0 + 0.5) / BIN - 0.5, abs=1e-12)
    assert cam.cy == pytest.approx((FULL.cy - y0 + 0.5) / BIN - 0.5, abs=1e-12)
    # image_geometry's (cx - x_offset) / b, less the half-pixel term (b - 1) / (2 b)
    assert cam.cx == pytest.approx((FULL.cx - x0) / BIN - (BIN - 1) / (2 * BIN), abs=1e-12)
    assert calib.D == D and calib.distortion_model == 'plumb_bob'
    # binning alone, ROI alone
    only_bin = m.camera_info_to_calibration(_info(kind, binning=(2, 1))).camera
    assert only_bin == PinholeCamera(100, 160, 90.0, 182.0, (101.3 + 0.5) / 2 - 0.5, 78.6)
    only_roi = m.camera_info_to_calibration(_info(kind, binning=(1, 0), roi=ROI)).camera
    assert only_roi == FULL.cropped(x0, y0, ROI['width'], ROI['height'])
    # nothing set (REP 104's zeros): the full sensor, exactly
    assert m.camera_info_to_calibration(_info(kind)).camera == FULL


def test_a_point_lands_where_the_adjusted_k_projects_it():
    """Project with the full-sensor K, map into the binned ROI grid by the pixel-centre rule
    ``u_b = (u - x_offset + 0.5) / b - 0.5``: the adjusted K gives the same pixel."""
    rng = np.random.default_rng(0)
    points = np.column_stack((rng.uniform(-1, 1, 500), rng.uniform(-1, 1, 500), rng.uniform(1, 5, 500)))
    window = ImageWindow.of(
        FULL.width,
        FULL.height,
        binning_x=BIN,
        binning_y=BIN,
        x_offset=ROI['x_offset'],
        y_offset=ROI['y_offset'],
        roi_width=ROI['width'],
        roi_height=ROI['height'],
    )
    binned = window.camera(FULL.fx, FULL.fy, FULL.cx, FULL.cy)
    uv_full, _ = FULL.project(points)
    mapped = (uv_full - [ROI['x_offset'], ROI['y_offset']] + 0.5) / BIN - 0.5
    uv_binned, _ = binned.project(points)
    np.testing.assert_allclose(uv_binned, mapped, rtol=0, atol=1e-10)
    # and the centre of binned pixel (j, i) is the centre of its b x b block of sensor pixels
    j, i = np.meshgrid(np.arange(binned.width), np.arange(binned.height))
    depth = np.full((binned.height, binned.width), 2.0)
    uv_sensor, _ = FULL.project(binned.backproject(depth))
    np.testing.assert_allclose(uv_sensor[..., 0], ROI['x_offset'] + j * BIN + (BIN - 1) / 2, atol=1e-9)
    np.testing.assert_allclose(uv_sensor[..., 1], ROI['y_offset'] + i * BIN + (BIN - 1) / 2, atol=1e-9)


def test_undistorting_the_binned_roi_matches_binning_the_undistorted_sensor_image():
    """D acts on normalised coordinates: undistorting the binned ROI with the adjusted K and the
    same D gives the binned ROI of the undistorted full image (a few grey levels of bilinear
    interpolation and rounding apart), while a wrong D or no undistortion is far off."""
    y, x = np.mgrid[0 : FULL.height, 0 : FULL.width].astype(np.float64)
    waves = [np.sin(2 * np.pi * x / 31 + 0.3) + np.cos(2 * np.pi * y / 27 + ph) for ph in (0, 1, 2)]
    raw = 128 + 50 * np.stack(waves, axis=-1)
    raw = np.clip(np.rint(raw), 0, 255).astype(np.uint8)
    full = Undistorter.for_calibration(CameraCalibration(FULL, 'plumb_bob', D), FULL.width, FULL.height)
    expected = _bin(_crop(full.rgb(raw)))
    binned_raw = _bin(_crop(raw))

    calib = m.camera_info_to_calibration(_info(TYPESTORE, binning=(BIN, BIN), roi=ROI))
    assert calib.camera.size == binned_raw.shape[1::-1]

    def error(calibration: CameraCalibration) -> np.ndarray:
        cam = calibration.camera
        out = Undistorter.for_calibration(calibration, cam.width, cam.height).rgb(binned_raw)
        return np.abs(out.astype(int) - expected.astype(int))[4:-4, 4:-4]  # away from the borders

    err = error(calib)
    assert err.max() <= 3 and err.mean() < 1.0, (err.max(), err.mean())
    wrong_d = dataclasses.replace(calib, D=(D[0] * 1.2, *D[1:]))
    assert error(wrong_d).max() > 8
    assert np.abs(binned_raw.astype(int) - expected.astype(int))[4:-4, 4:-4].max() > 30


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
def test_rectified_takes_p_and_drops_d(kind):
    P = np.array([[170.0, 0.0, 99.0, 0.0], [0.0, 171.0, 80.5, 0.0], [0.0, 0.0, 1.0, 0.0]])
    msg = _info(kind, P=P)
    raw = m.camera_info_to_calibration(msg)
    assert raw.camera == FULL and raw.D == D  # without the flag: K and D, as before
    rect = m.camera_info_to_calibration(msg, rectified=True)
    assert rect.camera == PinholeCamera(200, 160, 170.0, 171.0, 99.0, 80.5)
    assert rect.distortion_model == 'plumb_bob' and rect.D == () and not rect.is_distorted
    binned = m.camera_info_to_calibration(_info(kind, P=P, binning=(BIN, BIN), roi=ROI), rectified=True)
    assert binned.camera == ImageWindow.of(
        200, 160, binning_x=BIN, binning_y=BIN, x_offset=20, y_offset=16, roi_width=160, roi_height=128
    ).camera(170.0, 171.0, 99.0, 80.5)
    assert binned.camera.fx == 85.0 and binned.D == ()
    for bad in (np.zeros(12), np.full(12, np.nan)):
        with pytest.raises(ValueError, match='P is not set') as exc:
            m.camera_info_to_calibration(_info(kind, P=bad), rectified=True)
        assert '\n' not in str(exc.value)


@pytest.mark.parametrize(
    ('binning', 'roi', 'field'),
    [
        ((0, 0), dict(x_offset=100, y_offset=0, width=160, height=160), 'roi.width'),
        ((0, 0), dict(x_offset=0, y_offset=40, width=200, height=140), 'roi.height'),
        ((0, 0), dict(x_offset=5, y_offset=0, width=0, height=0), 'roi.x_offset'),
        ((3, 1), ROI, 'binning_x'),
        ((2, 3), ROI, 'binning_y'),
        ((-2, 0), {}, 'binning_x'),
        ((0, 0), dict(x_offset=0, y_offset=-1, width=0, height=100), 'roi.y_offset'),
    ],
)
def test_bad_roi_or_binning_is_a_one_line_error_naming_the_field(binning, roi, field):
    msg = _info(TYPESTORE, binning=binning, roi=roi)  # rosbags holds any int (rclpy refuses < 0)
    for rectified in (False, True):
        with pytest.raises(ValueError, match=field.replace('.', r'\.')) as exc:
            m.camera_info_to_calibration(msg, rectified=rectified)
        assert '\n' not in str(exc.value)
    with pytest.raises(InputError) as exc:
        CameraInput(32, 24).update(msg)
    assert exc.value.reason == 'bad_camera_info'


def test_camera_input_with_camera_rectified_only_resizes_and_without_it_undistorts():
    cam = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)
    P = np.array([[46.0, 0.0, 30.0, 0.0], [0.0, 47.0, 24.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    header = m.header_msg(1_000, 'cam', kind=m.RCLPY)
    info = _info(m.RCLPY, cam, (0.25, -0.1, 0.001, 0.002, 0.0), P=P)
    rgb = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    image = m.image_msg(rgb, 'rgb8', header, kind=m.RCLPY)
    plain = cv2.resize(rgb, (32, 24), interpolation=cv2.INTER_AREA)

    rectified = CameraInput(32, 24, camera_rectified=True)
    rectified.update(info)
    work = rectified.working_image(image)
    np.testing.assert_array_equal(work.rgb, plain)
    assert work.camera == PinholeCamera(64, 48, 46.0, 47.0, 30.0, 24.0).scaled(32, 24)

    raw = CameraInput(32, 24)
    raw.update(info)
    work = raw.working_image(image)
    assert work.camera == cam.scaled(32, 24)
    assert np.abs(work.rgb.astype(int) - plain.astype(int)).mean() > 5

    with pytest.raises(InputError, match='P is not set') as exc:
        rectified.update(_info(m.RCLPY, cam, P=np.zeros(12)))
    assert exc.value.reason == 'bad_camera_info'


def test_camera_rectified_is_a_parameter_read_by_from_parameters():
    from depth_fusion_ros.nodes import multi_view_node

    assert 'camera_rectified' in [s.name for s in multi_view_node.PARAMETERS]
    specs = {s.name: s for s in working_grid_parameters()}
    assert specs['camera_rectified'].default is False
    params = {s.name: s.default for s in specs.values()}
    assert not CameraInput.from_parameters(params).camera_rectified
    on = CameraInput.from_parameters({**params, 'camera_rectified': True})
    assert on.camera_rectified and not on.rectified  # not the keyframe topic's "no camera_info"


def test_an_image_of_camera_infos_own_size_under_binning_says_what_the_driver_did():
    """A driver that binned K itself and still says binning 2: the image has camera_info's own
    width x height, not the binned size. The drop says so, in one line, instead of a bare
    size mismatch."""
    inp = CameraInput(32, 24)
    inp.update(_info(m.RCLPY, binning=(BIN, BIN)))
    header = m.header_msg(1_000, 'cam', kind=m.RCLPY)
    same_as_info = m.rgb_image_msg(np.zeros((FULL.height, FULL.width, 3), np.uint8), header, kind=m.RCLPY)
    with pytest.raises(InputError) as exc:
        inp.working_image(same_as_info)
    assert exc.value.reason == 'size_mismatch'
    text = str(exc.value)
    assert 'image is 200x160 but camera_info says 100x80 after its binning and ROI' in text
    assert 'binning 0' in text and '\n' not in text
    binned = m.rgb_image_msg(np.zeros((FULL.height // 2, FULL.width // 2, 3), np.uint8), header, kind=m.RCLPY)
    assert inp.working_image(binned).rgb.shape == (24, 32, 3)
