"""TUM folder parsing, association, undistortion and the Sequence loader."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.tum import (
    associate,
    load_tum_sequence,
    read_camera_yaml,
    read_groundtruth,
    read_tum_index,
    read_tum_list,
)
from depth_fusion_ros.data.undistort import CameraCalibration, Undistorter
from depth_fusion_ros.geometry import invert_pose, make_pose, relative_pose

CAMERA_YAML = """\
image_width: {w}
image_height: {h}
camera_name: test
camera_matrix:
  rows: 3
  cols: 3
  data: [{fx}, 0.0, {cx}, 0.0, {fy}, {cy}, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [{d}]
"""


def write_camera_yaml(path: Path, cam: PinholeCamera, D=(0, 0, 0, 0, 0)) -> None:
    path.write_text(
        CAMERA_YAML.format(
            w=cam.width, h=cam.height, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, d=', '.join(map(str, D))
        )
    )


def make_tum_folder(
    root: Path,
    n: int = 6,
    size: tuple[int, int] = (64, 48),
    rgb_t0: float = 100.0,
    gt_span: tuple[float, float] | None = None,
    depth_offset: float = 0.004,
    missing_depth: tuple[int, ...] = (),
    D: tuple[float, ...] = (0, 0, 0, 0, 0),
) -> dict:
    """A small TUM folder: colour at 10 Hz from ``rgb_t0``, depth 4 ms later, 100 Hz poses."""
    w, h = size
    cam = PinholeCamera(w, h, 50.0, 52.0, w / 2 - 0.5, h / 2 - 0.5)
    (root / 'rgb').mkdir(parents=True)
    (root / 'depth').mkdir()
    rng = np.random.default_rng(0)
    rgb_lines, depth_lines, truth = ['# color images', '# timestamp filename'], ['# depth'], {}
    for i in range(n):
        t = rgb_t0 + 0.1 * i
        rgb = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
        cv2.imwrite(str(root / 'rgb' / f'{t:.6f}.png'), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        rgb_lines.append(f'{t:.6f} rgb/{t:.6f}.png')
        truth[round(t * 1e6)] = {'rgb': rgb}
        if i in missing_depth:
            continue
        td = t + depth_offset
        raw = rng.integers(0, 20000, (h, w)).astype(np.uint16)
        raw[0, :5] = 0
        cv2.imwrite(str(root / 'depth' / f'{td:.6f}.png'), raw)
        depth_lines.append(f'{td:.6f} depth/{td:.6f}.png')
        truth[round(t * 1e6)]['depth_raw'] = raw
    t0, t1 = gt_span or (rgb_t0 - 0.05, rgb_t0 + 0.1 * n)
    gt_lines = ['# ground truth', '# timestamp tx ty tz qx qy qz qw']
    for t in np.arange(t0, t1, 0.01):
        gt_lines.append(f'{t:.4f} {0.5 * (t - t0):.6f} 0.1 -0.2 0 0 0 1')
    (root / 'rgb.txt').write_text('\n'.join(rgb_lines) + '\n')
    (root / 'depth.txt').write_text('\n'.join(depth_lines) + '\n')
    (root / 'groundtruth.txt').write_text('\n'.join(gt_lines) + '\n')
    write_camera_yaml(root / 'camera.yaml', cam, D)
    return {'camera': cam, 'truth': truth, 'gt_t0': t0}


def test_loads_a_small_folder_exactly(tmp_path):
    info = make_tum_folder(tmp_path, n=6)
    seq = load_tum_sequence(tmp_path, width=32, height=24)
    assert len(seq) == 6 and seq.dropped == {}
    assert seq.gt_camera == info['camera'] and seq.camera == info['camera'].scaled(32, 24)
    for f in seq.frames:
        truth = info['truth'][round(f.stamp * 1e6)]
        expected_rgb = cv2.resize(truth['rgb'], (32, 24), interpolation=cv2.INTER_AREA)
        np.testing.assert_array_equal(f.rgb, expected_rgb)
        raw = truth['depth_raw']
        assert f.depth.shape == (48, 64) and f.depth.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(f.depth), raw == 0)
        np.testing.assert_allclose(f.depth[raw > 0], raw[raw > 0] / 5000.0, rtol=1e-6)
        # pose interpolated at the colour stamp: tx = 0.5 * (t - t0)
        np.testing.assert_allclose(f.pose[:3, 3], [0.5 * (f.stamp - info['gt_t0']), 0.1, -0.2], atol=1e-9)
    assert seq.frames[0].stamp == 100.0 and seq.frames[1].stamp == 100.1


def test_max_frames_and_working_size(tmp_path):
    make_tum_folder(tmp_path, n=6)
    seq = load_tum_sequence(tmp_path, width=16, height=12, max_frames=3)
    assert len(seq) == 3 and seq.frames[0].rgb.shape == (12, 16, 3)
    assert [f.index for f in seq.frames] == [0, 1, 2]


def test_comments_blank_and_unsorted_lines(tmp_path):
    make_tum_folder(tmp_path, n=5)
    for name in ('rgb.txt', 'depth.txt', 'groundtruth.txt'):
        path = tmp_path / name
        lines = path.read_text().splitlines()
        data = [ln for ln in lines if not ln.startswith('#')]
        path.write_text('\n'.join(['# header', '', *reversed(data), '   ', '# trailing comment']) + '\n')
    seq = load_tum_sequence(tmp_path, width=32, height=24)
    assert len(seq) == 5
    assert np.all(np.diff(seq.stamps) > 0)


def test_frames_outside_groundtruth_and_without_depth_are_counted(tmp_path):
    # colour at 100.0 .. 100.7; ground truth only covers 100.15 .. 100.55
    make_tum_folder(tmp_path, n=8, gt_span=(100.15, 100.56), missing_depth=(3,))
    seq = load_tum_sequence(tmp_path, width=32, height=24)
    assert [round(f.stamp, 3) for f in seq.frames] == [100.2, 100.4, 100.5]
    assert seq.dropped == {'outside_groundtruth': 4, 'no_depth': 1}
    # without requiring depth, the frame without depth stays, with depth None
    seq = load_tum_sequence(tmp_path, width=32, height=24, require_depth=False)
    assert len(seq) == 4 and seq.frames[1].depth is None
    assert seq.dropped == {'outside_groundtruth': 4}


def test_depth_gap_is_respected(tmp_path):
    make_tum_folder(tmp_path, n=3, depth_offset=0.03)
    seq = load_tum_sequence(tmp_path, width=32, height=24)
    assert len(seq) == 0 and seq.dropped == {'no_depth': 3}
    assert len(load_tum_sequence(tmp_path, width=32, height=24, depth_max_gap=0.031)) == 3


def test_malformed_line_names_file_and_line(tmp_path):
    make_tum_folder(tmp_path, n=3)
    rgb_txt = tmp_path / 'rgb.txt'
    lines = rgb_txt.read_text().splitlines()
    lines.insert(3, '100.250000')  # line 4: no filename
    rgb_txt.write_text('\n'.join(lines) + '\n')
    with pytest.raises(ValueError, match=r'rgb\.txt:4: expected "timestamp filename"'):
        load_tum_sequence(tmp_path)
    lines[3] = 'abc rgb/x.png'
    rgb_txt.write_text('\n'.join(lines) + '\n')
    with pytest.raises(ValueError, match=r"rgb\.txt:4: not a timestamp: 'abc'"):
        read_tum_list(rgb_txt)
    gt = tmp_path / 'groundtruth.txt'
    gt.write_text('# c\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n')
    with pytest.raises(ValueError, match=r'groundtruth\.txt:3: expected "timestamp tx ty tz qx qy qz qw"'):
        read_groundtruth(gt)
    gt.write_text('1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n')
    with pytest.raises(ValueError, match=r'groundtruth\.txt:2: pose has non-finite'):
        read_groundtruth(gt)


def test_duplicate_stamps_name_the_file(tmp_path):
    make_tum_folder(tmp_path, n=3)
    depth_txt = tmp_path / 'depth.txt'
    lines = depth_txt.read_text().splitlines()
    depth_txt.write_text('\n'.join([*lines, lines[-1]]) + '\n')
    with pytest.raises(
        ValueError, match=r'depth\.txt:5: duplicate timestamp 100\.204000000 \(also on line 4\)'
    ):
        load_tum_sequence(tmp_path)


def test_missing_files_raise_naming_the_path(tmp_path):
    make_tum_folder(tmp_path, n=3)
    (tmp_path / 'camera.yaml').unlink()
    with pytest.raises(FileNotFoundError, match=r'camera\.yaml'):
        load_tum_sequence(tmp_path)
    write_camera_yaml(tmp_path / 'camera.yaml', PinholeCamera(64, 48, 50, 50, 32, 24))
    missing = sorted((tmp_path / 'rgb').iterdir())[1]
    missing.unlink()
    with pytest.raises(FileNotFoundError, match=missing.name):
        load_tum_sequence(tmp_path)
    missing.write_bytes(b'not a png')
    with pytest.raises(ValueError, match=f'cannot decode image file .*{missing.name}'):
        load_tum_sequence(tmp_path)
    with pytest.raises(FileNotFoundError, match='nowhere'):
        load_tum_sequence(tmp_path / 'nowhere')


def test_wrong_image_size_names_the_file(tmp_path):
    make_tum_folder(tmp_path, n=3)
    write_camera_yaml(tmp_path / 'camera.yaml', PinholeCamera(640, 480, 500, 500, 320, 240))
    with pytest.raises(ValueError, match=r'rgb/100\.000000\.png: image is 64x48, camera\.yaml says 640x480'):
        load_tum_sequence(tmp_path)


def test_depth_must_be_16_bit(tmp_path):
    make_tum_folder(tmp_path, n=2)
    first = sorted((tmp_path / 'depth').iterdir())[0]
    cv2.imwrite(str(first), np.zeros((48, 64), np.uint8))
    with pytest.raises(ValueError, match=f'{first.name}: a depth image must be single-channel 16-bit'):
        load_tum_sequence(tmp_path)


def test_camera_yaml_errors(tmp_path):
    path = tmp_path / 'camera.yaml'
    path.write_text('image_width: 10\nimage_height: 10\n')
    with pytest.raises(ValueError, match='camera_matrix'):
        read_camera_yaml(path)
    write_camera_yaml(path, PinholeCamera(64, 48, 50, 50, 32, 24), D=(0.1, 0.2))
    with pytest.raises(ValueError, match=r'camera\.yaml: distortion model .plumb_bob. needs'):
        read_camera_yaml(path)
    path.write_text(path.read_text().replace('plumb_bob', 'kannala_brandt'))
    with pytest.raises(ValueError, match='unsupported distortion model'):
        read_camera_yaml(path)


def test_index_and_association_api(tmp_path):
    make_tum_folder(tmp_path, n=4)
    index = read_tum_index(tmp_path)
    assoc = associate(index, max_frames=2)
    assert len(assoc.frames) == 2
    f = assoc.frames[0]
    assert f.stamp_ns == 100_000_000_000 and f.depth_stamp_ns == 100_004_000_000
    assert f.rgb_file.name == '100.000000.png' and f.depth_file.name == '100.004000.png'


def test_undistortion_moves_points_to_their_pinhole_projection():
    """A dot drawn where the distorted camera sees a 3D point lands, after undistortion,
    where the ideal pinhole camera projects that point."""
    cam = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3)
    D = np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])
    und = Undistorter(cam, 'plumb_bob', D, 640, 480)
    points = np.array([[0.4, 0.3, 1.0], [-0.5, -0.35, 1.0], [0.1, -0.2, 1.0]])
    raw_px, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, D)
    raw = _dots((480, 640), raw_px, 4)
    ideal, _ = cam.project(points)
    _assert_dots_at(und.rgb(raw), ideal, 0.3)
    # the raw dots were far from the ideal positions (so the test is meaningful)
    assert np.max(np.abs(raw_px.reshape(-1, 2) - ideal)) > 5
    depth = und.depth(np.ones((480, 640), np.float32))
    assert np.isnan(depth).any() and set(np.unique(depth[np.isfinite(depth)])) == {1.0}


def _dots(shape: tuple[int, int], centres: np.ndarray, radius: int) -> np.ndarray:
    """White anti-aliased discs on black at sub-pixel ``centres`` (8 fractional bits, so
    rounding does not blur the check)."""
    raw = np.zeros((*shape, 3), np.uint8)
    for x, y in centres.reshape(-1, 2):
        cv2.circle(raw, (round(x * 256), round(y * 256)), radius * 256, (255, 255, 255), -1, cv2.LINE_AA, 8)
    return raw


def _assert_dots_at(image: np.ndarray, ideal: np.ndarray, tolerance: float) -> None:
    """Each dot's intensity centroid (17 px window) is within ``tolerance`` px of ``ideal``."""
    grey = image[..., 0].astype(np.float64)
    yy, xx = np.mgrid[-8:9, -8:9]
    for u, v in ideal:
        y0, x0 = round(v), round(u)
        win = grey[y0 - 8 : y0 + 9, x0 - 8 : x0 + 9]
        cy, cx = (win * yy).sum() / win.sum(), (win * xx).sum() / win.sum()
        assert abs(cx - (u - x0)) < tolerance and abs(cy - (v - y0)) < tolerance, (u, v, cx, cy)


@pytest.mark.parametrize('size', [(1296, 972), (1280, 720)])
def test_undistorter_box_filters_a_large_camera_first_where_the_geometry_says(size):
    """A 1296x972 or 1280x720 camera for a 320x240 grid is box-filtered by 2 before the
    undistortion (the cost of a 640x480 camera, docs/nodes.md); dots still land where the
    ideal pinhole camera of the working grid projects them, and the picture matches the
    full-size undistortion followed by an area resize to within a grey level on average."""
    width, height = size
    vga = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3)
    cam = vga.scaled(width, height)
    D = np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])
    und = Undistorter(cam, 'plumb_bob', D, 320, 240)
    assert und.shrink == 2 and und.shrunk_size == (width // 2, height // 2)
    assert Undistorter(vga, 'plumb_bob', D, 320, 240).shrink == 1  # the evaluation's data: as before
    points = np.array([[0.4, 0.3, 1.0], [-0.5, -0.35, 1.0], [0.1, -0.2, 1.0], [0.0, 0.0, 1.0]])
    raw_px, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, D)
    raw = _dots((height, width), raw_px, 16)
    out = und.rgb(raw)
    assert out.shape == (240, 320, 3)
    ideal, _ = und.camera.project(points)
    _assert_dots_at(out, ideal, 0.15)
    maps = cv2.initUndistortRectifyMap(cam.K, D, None, cam.K, cam.size, cv2.CV_32FC1)
    full = cv2.resize(cv2.remap(raw, *maps, cv2.INTER_LINEAR), (320, 240), interpolation=cv2.INTER_AREA)
    assert np.abs(full.astype(np.float64) - out).mean() < 1.0
    # the ground-truth depth keeps the full-size maps (built when first asked for)
    depth = und.depth(np.ones((height, width), np.float32))
    assert depth.shape == (height, width) and np.isnan(depth).any()


def test_undistorter_cache_and_errors():
    cam = PinholeCamera(64, 48, 50, 50, 32, 24)
    calib = CameraCalibration(cam, 'plumb_bob', (0.1, 0, 0, 0, 0))
    assert Undistorter.for_calibration(calib, 32, 24) is Undistorter.for_calibration(calib, 32, 24)
    assert Undistorter.for_calibration(calib, 32, 24) is not Undistorter.for_calibration(calib, 16, 12)
    with pytest.raises(ValueError, match='unsupported distortion model'):
        Undistorter(cam, 'fov', (0.1,))
    with pytest.raises(ValueError, match='colour image is 10x10'):
        Undistorter(cam, 'plumb_bob', (0.1, 0, 0, 0, 0)).rgb(np.zeros((10, 10, 3), np.uint8))
    # equidistant (fisheye) is supported through cv2.fisheye
    fish = Undistorter(cam, 'equidistant', (0.05, 0.01, 0, 0), 64, 48)
    assert fish.rgb(np.full((48, 64, 3), 9, np.uint8))[24, 32, 0] == 9


def _warp_error(seq, k: int, j: int, T_jk: np.ndarray | None = None) -> float:
    """Median relative difference between frame k's depth warped into frame j and frame j's depth."""
    cam = seq.gt_camera
    a, b = seq.frames[k], seq.frames[j]
    T = relative_pose(a.pose, b.pose) if T_jk is None else T_jk
    P = cam.backproject(a.depth).reshape(-1, 3)
    P = P[np.isfinite(P[:, 2])]
    uv, z = cam.project(P @ T[:3, :3].T + T[:3, 3])
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    inside = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    d = b.depth[v[inside], u[inside]]
    valid = np.isfinite(d)
    assert valid.sum() > 0.3 * cam.width * cam.height, 'too little overlap to judge'
    return float(np.median(np.abs(z[inside][valid] - d[valid]) / d[valid]))


def test_tum_fr1_xyz_loads_and_is_geometrically_consistent(tum_fr1_xyz):
    seq = load_tum_sequence(tum_fr1_xyz)
    assert len(seq) == 37 and seq.dropped == {}
    assert seq.camera.size == (320, 240) and seq.gt_camera.size == (640, 480)
    assert seq.frames[0].rgb.shape == (240, 320, 3) and seq.frames[0].depth.shape == (480, 640)
    # distortion removed: the border of the undistorted depth has NaN where nothing maps
    assert np.isnan(seq.frames[0].depth[:, 0]).all()
    for k in (0, 15, 30):
        err = _warp_error(seq, k, k + 5)
        wrong = _warp_error(
            seq, k, k + 5, invert_pose(relative_pose(seq.frames[k].pose, seq.frames[k + 5].pose))
        )
        assert err < 0.03, (k, err)
        assert wrong > 3 * err, (k, err, wrong)


def test_7scenes_redkitchen_is_geometrically_consistent(redkitchen):
    seq = load_tum_sequence(redkitchen, max_frames=41)
    assert len(seq) == 41 and seq.gt_camera.fx == 585.0
    err = _warp_error(seq, 0, 40)
    identity = _warp_error(seq, 0, 40, np.eye(4))
    assert err < 0.05, err
    assert identity > 3 * err, (err, identity)


def test_make_pose_sanity():
    # guards the helper maths the warp test relies on
    T = make_pose([1, 2, 3], [0, 0, 0.3826834, 0.9238795])
    np.testing.assert_allclose(relative_pose(T, T), np.eye(4), atol=1e-12)
