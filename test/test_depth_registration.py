"""Ground truth from a depth camera with other intrinsics than the colour camera (7-Scenes)."""

from __future__ import annotations

import numpy as np
import yaml

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.synthetic import SynthConfig, build_world, render_frame
from depth_fusion_ros.data.tum import load_tum_sequence, read_camera_yaml, register_depth
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
