"""Ground truth from a depth camera with other intrinsics than the colour camera, and a
baseline between the two (7-Scenes)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.depth_registration import register_depth
from depth_fusion_ros.data.synthetic import SynthConfig, build_world, render_frame
from depth_fusion_ros.data.tum import load_tum_sequence, read_camera_yaml
from depth_fusion_ros.data.tum_writer import write_tum_folder

COLOUR = PinholeCamera(160, 120, 131.25, 131.25, 80.0, 60.0)  # 525 px at 640x480
DEPTH = PinholeCamera(160, 120, 146.25, 146.25, 80.0, 60.0)  # 585 px at 640x480


def two_camera_views(n: int = 2):
    cfg = SynthConfig(width=160, height=120, frames=n, seed=3)
    scene, trajectory = build_world(cfg)
    colour = [render_frame(scene, COLOUR, T, antialias=False) for T in trajectory.poses]
    depth = [render_frame(scene, DEPTH, T, antialias=False) for T in trajectory.poses]
    return trajectory.poses, colour, depth


def rel_diff(a: np.ndarray, b: np.ndarray, q: float = 90) -> float:
    """``q``-th percentile of the relative difference (edges misplaced by a wrong focal length
    show in the tail, smooth surfaces hide it in the median)."""
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.percentile(np.abs(a[ok] - b[ok]) / b[ok], q))


def test_register_depth_matches_the_colour_cameras_own_depth():
    _, colour, depth = two_camera_views(1)
    registered = register_depth(depth[0].depth, DEPTH, COLOUR)
    assert rel_diff(registered, colour[0].depth, 50) < 1e-3
    assert rel_diff(registered, colour[0].depth) < 0.01
    # the wider colour view sees beyond the depth camera's border: no estimate there
    assert np.isnan(registered[:, 0]).all() and np.isfinite(registered[60, 80])
    # without registration the ground truth is visibly wrong for the colour image
    assert rel_diff(depth[0].depth, colour[0].depth) > 0.03


def _moved(b: float) -> np.ndarray:
    """The colour camera ``b`` metres along the depth camera's x axis."""
    T = np.eye(4)
    T[0, 3] = b
    return T


def test_a_colour_camera_beside_the_depth_camera_sees_its_own_depth():
    """A Kinect's colour camera sits 2.5 cm beside its depth camera. From its own centre the
    registered depth is the colour camera's rendered depth (1 % off at the 99th percentile:
    pixel rounding at the edges); taken as the same centre, the near surfaces' outlines land
    pixels off the far ones' (half the depth off at the 99th percentile)."""
    cfg = SynthConfig(width=160, height=120, frames=1, seed=3)
    scene, trajectory = build_world(cfg)
    T = trajectory.poses[0]
    colour = render_frame(scene, COLOUR, T @ _moved(0.025), antialias=False).depth
    depth = render_frame(scene, DEPTH, T, antialias=False).depth
    registered = register_depth(depth, DEPTH, COLOUR, (0.025, 0.0, 0.0))
    assert rel_diff(registered, colour, 95) < 0.01 and rel_diff(registered, colour, 99) < 0.03
    assert rel_diff(register_depth(depth, DEPTH, COLOUR), colour, 99) > 0.3
    assert np.isnan(registered).mean() < 0.21  # the border the depth camera does not see, and shadows


def _colour_yaml(path, **extra) -> None:
    doc = {
        'image_width': 160,
        'image_height': 120,
        'camera_matrix': {'rows': 3, 'cols': 3, 'data': COLOUR.K.ravel().tolist()},
        'distortion_model': 'plumb_bob',
        'distortion_coefficients': {'rows': 1, 'cols': 5, 'data': [0.0] * 5},
    }
    path.write_text(yaml.safe_dump({**doc, **extra}))


def test_the_loader_registers_from_the_centre_the_colour_yaml_gives(tmp_path):
    """``centre_in_depth_camera`` in the colour YAML moves the registration's centre; the poses
    stay the folder's. A malformed centre is a one-line error naming the file."""
    cfg = SynthConfig(width=160, height=120, frames=2, seed=3)
    scene, trajectory = build_world(cfg)
    poses = trajectory.poses
    colour = [render_frame(scene, COLOUR, T @ _moved(0.025), antialias=False) for T in poses]
    depth = [render_frame(scene, DEPTH, T, antialias=False) for T in poses]
    stamps = np.array([10.0, 10.1])
    images, depths = [c.rgb for c in colour], [d.depth for d in depth]
    folder = write_tum_folder(tmp_path / 'seq', DEPTH, stamps, images, depths, poses)
    _colour_yaml(tmp_path / 'rgb.yaml', centre_in_depth_camera=[0.025, 0.0, 0.0])
    calibration = read_camera_yaml(tmp_path / 'rgb.yaml')
    assert calibration.centre_in_depth_camera == (0.025, 0.0, 0.0)
    seq = load_tum_sequence(folder, width=80, height=60, rgb_calibration=calibration)
    assert rel_diff(seq.frames[1].depth, colour[1].depth, 95) < 0.01
    assert rel_diff(seq.frames[1].depth, colour[1].depth, 99) < 0.05
    assert np.allclose(seq.frames[1].pose, poses[1])
    _colour_yaml(tmp_path / 'same.yaml')
    same_centre = read_camera_yaml(tmp_path / 'same.yaml')
    same = load_tum_sequence(folder, width=80, height=60, rgb_calibration=same_centre)
    assert rel_diff(same.frames[1].depth, colour[1].depth, 99) > 0.3
    for bad in ([0.025, 0.0], [0.025, 0.0, 'x'], [2.0, 0.0, 0.0]):
        _colour_yaml(tmp_path / 'bad.yaml', centre_in_depth_camera=bad)
        with pytest.raises(ValueError, match=r'bad\.yaml: .*centre_in_depth_camera') as error:
            read_camera_yaml(tmp_path / 'bad.yaml')
        assert '\n' not in str(error.value)


def test_loader_registers_depth_into_an_overridden_colour_camera(tmp_path):
    poses, colour, depth = two_camera_views(2)
    folder = write_tum_folder(
        tmp_path / 'seq',
        DEPTH,
        np.array([10.0, 10.1]),
        [c.rgb for c in colour],
        [d.depth for d in depth],
        poses,
    )  # camera.yaml holds the depth camera, as in 7-Scenes
    rgb_yaml = tmp_path / 'rgb.yaml'
    rgb_yaml.write_text(
        yaml.safe_dump(
            {
                'image_width': 160,
                'image_height': 120,
                'camera_matrix': {'rows': 3, 'cols': 3, 'data': COLOUR.K.ravel().tolist()},
                'distortion_model': 'plumb_bob',
                'distortion_coefficients': {'rows': 1, 'cols': 5, 'data': [0.0] * 5},
            }
        )
    )
    seq = load_tum_sequence(folder, width=80, height=60, rgb_calibration=read_camera_yaml(rgb_yaml))
    assert seq.gt_camera == COLOUR and seq.camera == COLOUR.scaled(80, 60)
    assert rel_diff(seq.frames[1].depth, colour[1].depth) < 0.01
    plain = load_tum_sequence(folder, width=80, height=60)
    assert rel_diff(plain.frames[1].depth, colour[1].depth) > 0.03


def _diag(name: str):
    """A diagnostic script of scripts/diag as a module."""
    path = Path(__file__).resolve().parents[1] / 'scripts' / 'diag' / f'{name}.py'
    spec = importlib.util.spec_from_file_location(f'diag_{name}', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_independent_live_client_registers_as_the_evaluation_does():
    """scripts/diag/live_client.py uses no project code; its ground truth from a colour camera
    beside the depth camera is the evaluation's, pixel for pixel."""
    cfg = SynthConfig(width=160, height=120, frames=1, seed=3)
    scene, trajectory = build_world(cfg)
    depth = render_frame(scene, DEPTH, trajectory.poses[0], antialias=False).depth
    centre = np.array([0.025, 0.005, 0.0])
    ours = register_depth(depth, DEPTH, COLOUR, tuple(centre))
    client = _diag('live_client').projected_depth(np.nan_to_num(depth), DEPTH.K, COLOUR.K, (160, 120), centre)
    assert np.array_equal(np.nan_to_num(ours), client)


def test_the_baseline_diagnostic_finds_where_the_colour_camera_is():
    """scripts/diag/depth_colour_baseline.py scores candidate centres by the colour gradient
    under the registered depth's edges: on a rendered rig whose colour camera is 2.5 cm along
    x, the true centre scores highest, above the same-centre registration and the far side."""
    edge_contrast = _diag('depth_colour_baseline').edge_contrast
    cfg = SynthConfig(width=160, height=120, frames=3, seed=3)
    scene, trajectory = build_world(cfg)
    scores = {x: [] for x in (-0.025, 0.0, 0.025, 0.05)}
    for T in trajectory.poses:
        image = render_frame(scene, COLOUR, T @ _moved(0.025), antialias=False).rgb
        grey = image.mean(axis=2).astype(np.float32)
        gradient = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
        depth = render_frame(scene, DEPTH, T, antialias=False).depth
        for x, s in scores.items():
            s.append(edge_contrast(register_depth(depth, DEPTH, COLOUR, (x, 0.0, 0.0)), gradient))
    mean = {x: float(np.mean(s)) for x, s in scores.items()}
    assert max(mean, key=mean.get) == 0.025, mean
