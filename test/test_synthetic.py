"""Synthetic sequences: exact geometry, photometric consistency, determinism, TUM output."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.sequence import Sequence
from depth_fusion_ros.data.synthetic import (
    SynthConfig,
    build_world,
    render_frame,
    render_sequence,
)
from depth_fusion_ros.data.tum_writer import DEPTH_SCALE, png16_to_depth, write_tum_folder
from depth_fusion_ros.geometry import quat_to_matrix, relative_pose, rotation_angle

GAP = 5  # frames between the two views of the consistency checks


def warp_into(camera: PinholeCamera, depth_k: np.ndarray, T_wk: np.ndarray, T_wj: np.ndarray):
    """Project frame k's pixels (with its depth) into frame j: ``(map_x, map_y, z_in_j)``."""
    T_jk = relative_pose(T_wk, T_wj)
    points = camera.backproject(depth_k) @ T_jk[:3, :3].T + T_jk[:3, 3]
    uv, z = camera.project(points)
    return uv[..., 0].astype(np.float32), uv[..., 1].astype(np.float32), z


def smooth_depth_mask(depth: np.ndarray, radius: int = 2) -> np.ndarray:
    """Pixels at least ``radius`` px away from occlusion edges and creases.

    Inverse depth is affine across a plane in the image, so its Laplacian vanishes on every
    planar surface and is large only where surfaces meet.
    """
    inv = (1.0 / depth).astype(np.float32)
    edge = np.abs(cv2.Laplacian(inv, cv2.CV_32F, ksize=1)) > 1e-3 * inv
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.dilate(edge.astype(np.uint8), kernel) == 0


def covisible(camera, frame_k, frame_j):
    """Warp of k into j plus the mask of pixels visible in both, away from occlusion edges."""
    map_x, map_y, z = warp_into(camera, frame_k.depth, frame_k.pose, frame_j.pose)
    inside = (map_x > 2) & (map_x < camera.width - 3) & (map_y > 2) & (map_y < camera.height - 3) & (z > 0)
    # Inverse depth is affine across a plane in the image, so it interpolates exactly.
    inv_j = cv2.remap(1.0 / frame_j.depth, map_x, map_y, cv2.INTER_LINEAR, borderValue=0.0)
    smooth_j = cv2.remap(smooth_depth_mask(frame_j.depth).astype(np.uint8), map_x, map_y, cv2.INTER_NEAREST)
    depth_j = 1.0 / np.maximum(inv_j, 1e-6)
    visible = inside & smooth_depth_mask(frame_k.depth) & (smooth_j > 0) & (z < depth_j * 1.05)
    return map_x, map_y, z, depth_j, visible


def test_config_validation_names_the_parameter():
    with pytest.raises(ValueError, match='parallax'):
        SynthConfig(parallax='medium')
    with pytest.raises(ValueError, match='frames'):
        SynthConfig(frames=0)
    with pytest.raises(ValueError, match='textureless_fraction'):
        SynthConfig(textureless_fraction=1.5)
    cam = SynthConfig().camera()
    assert (cam.width, cam.height, cam.fx, cam.cx, cam.cy) == (640, 480, 525.0, 319.5, 239.5)
    assert SynthConfig(width=320, height=240).camera() == cam.scaled(320, 240)


def test_sequence_layout(synthetic_sequence: Sequence):
    seq = synthetic_sequence
    assert len(seq) == 24
    assert seq.camera == seq.gt_camera and (seq.camera.width, seq.camera.height) == (320, 240)
    assert np.allclose(np.diff(seq.stamps), 1 / 30, atol=2e-6)
    for f in seq.frames:
        assert f.rgb.shape == (240, 320, 3) and f.rgb.dtype == np.uint8
        assert f.depth.shape == (240, 320) and f.depth.dtype == np.float32
        assert np.all(np.isfinite(f.depth))
        assert np.allclose(f.pose[:3, :3].T @ f.pose[:3, :3], np.eye(3), atol=1e-9)
    depths = np.stack([f.depth for f in seq.frames])
    assert depths.min() > 0.5 and np.percentile(depths, 99) < 6.5  # indoor range


def test_geometric_consistency(synthetic_sequence: Sequence):
    """Depth of frame k warped into frame k+5 equals frame k+5's depth (within 1 %)."""
    seq = synthetic_sequence
    for k in (0, 9, 18):
        _, _, z, depth_j, visible = covisible(seq.camera, seq.frames[k], seq.frames[k + GAP])
        assert visible.mean() > 0.4, f'too little overlap between frames {k} and {k + GAP}'
        rel = np.abs(z[visible] - depth_j[visible]) / depth_j[visible]
        assert np.median(rel) < 0.01
        assert np.percentile(rel, 90) < 0.01


def test_photometric_consistency(synthetic_sequence: Sequence):
    """The colour of textured surfaces carried by the warp matches: brightness constancy."""
    seq = synthetic_sequence
    scene, _ = build_world(SynthConfig(width=320, height=240, frames=24, seed=0))
    k = 6
    frame_k, frame_j = seq.frames[k], seq.frames[k + GAP]
    textured = scene.surface_textured[render_frame(scene, seq.camera, frame_k.pose).surface]
    map_x, map_y, z, depth_j, visible = covisible(seq.camera, frame_k, frame_j)
    mask = visible & textured & (np.abs(z - depth_j) < 0.01 * depth_j)
    warped = cv2.remap(frame_j.rgb, map_x, map_y, cv2.INTER_LINEAR).astype(np.float32)
    diff = np.abs(warped - frame_k.rgb.astype(np.float32)).mean(axis=2)[mask]
    assert mask.sum() > 5000
    assert np.median(diff) < 3.0, np.median(diff)
    # The same comparison without the geometry (plain frame difference) is far worse, so the
    # check above is not passing on flat colour.
    plain = np.abs(frame_j.rgb.astype(np.float32) - frame_k.rgb).mean(axis=2)[mask]
    assert np.median(plain) > 3 * np.median(diff)


def test_textured_vs_textureless_gradients():
    """Texture-less surfaces have almost no image gradient, textured ones a lot."""
    cfg = SynthConfig(width=320, height=240, frames=1, seed=2, textureless_fraction=0.5)
    scene, trajectory = build_world(cfg)
    frame = render_frame(
        scene, cfg.camera(), trajectory.poses[0], noise_sigma=1.5, rng=np.random.default_rng(0)
    )
    grey = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8
    high = np.hypot(gx, gy) > 0.02  # 5 grey levels per pixel: far above the sensor noise
    interior = np.zeros_like(high)
    for s in np.unique(frame.surface):  # away from silhouettes and creases
        region = cv2.erode((frame.surface == s).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        interior |= region
    textured = interior & frame.textured
    flat = interior & ~frame.textured
    assert textured.sum() > 2000 and flat.sum() > 2000
    assert high[textured].mean() > 0.3
    assert high[flat].mean() < 0.01


def test_parallax_modes_share_the_room_but_not_the_baseline():
    high = SynthConfig(width=64, height=48, frames=30, seed=5, parallax='high')
    low = SynthConfig(width=64, height=48, frames=30, seed=5, parallax='low')
    scene_h, traj_h = build_world(high)
    scene_l, traj_l = build_world(low)
    assert np.array_equal(scene_h.centres, scene_l.centres)  # same room for both regimes
    pos_h, pos_l = traj_h.positions, traj_l.positions
    baseline_h = np.linalg.norm(pos_h[-1] - pos_h[0])
    baseline_l = np.linalg.norm(pos_l - pos_l[0], axis=1).max()
    assert 0.55 <= baseline_h <= 1.3
    assert baseline_l < 0.08
    assert baseline_h > 10 * baseline_l
    # Low parallax still moves the view: it rotates.
    assert np.rad2deg(rotation_angle(traj_l.poses[0][:3, :3].T @ traj_l.poses[-1][:3, :3])) > 15
    # Every camera stays inside the room and clear of the furniture.
    for traj, scene in ((traj_h, scene_h), (traj_l, scene_l)):
        for obj in range(1, scene.n_objects):
            local = (traj.positions - scene.centres[obj]) @ scene.rotations[obj]
            assert np.all(np.max(np.abs(local) - scene.halves[obj], axis=1) > 0.5)
        assert np.all(np.abs(traj.positions - scene.centres[0]) < scene.halves[0])


def test_determinism_and_seed_variety():
    cfg = SynthConfig(width=96, height=72, frames=3, seed=11)
    a, b = render_sequence(cfg), render_sequence(cfg)
    for fa, fb in zip(a.frames, b.frames, strict=True):
        assert np.array_equal(fa.rgb, fb.rgb) and np.array_equal(fa.depth, fb.depth)
        assert np.array_equal(fa.pose, fb.pose)
    c = render_sequence(SynthConfig(width=96, height=72, frames=3, seed=12))
    assert not np.array_equal(a.frames[0].depth, c.frames[0].depth)
    assert np.abs(a.frames[0].rgb.astype(int) - c.frames[0].rgb).mean() > 10
    rooms = [build_world(SynthConfig(width=32, height=24, frames=2, seed=s))[0] for s in range(3)]
    layouts = {tuple(np.round(r.centres[1:3].ravel(), 3)) for r in rooms}
    assert len(layouts) == 3
    assert len({tuple(np.round(r.room, 3)) for r in rooms}) == 3


def test_render_frame_is_exact_on_the_room_planes():
    """A pixel's depth back-projects onto the surface the renderer reports it hit."""
    cfg = SynthConfig(width=160, height=120, frames=2, seed=1, boxes=0, tables=0)
    scene, trajectory = build_world(cfg)
    camera = cfg.camera()
    T = trajectory.poses[1]
    frame = render_frame(scene, camera, T)
    world = camera.backproject(frame.depth) @ T[:3, :3].T + T[:3, 3]
    floor = frame.surface == 5
    ceiling_or_wall = ~floor
    assert floor.sum() > 1000
    assert np.abs(world[floor][:, 2]).max() < 1e-4
    half = scene.halves[0]
    on_boundary = np.min(np.abs(np.abs(world - scene.centres[0]) - half), axis=-1)
    assert on_boundary[ceiling_or_wall].max() < 1e-4


def test_write_synthetic_sequence(synthetic_tum_dir, synthetic_sequence: Sequence):
    path = synthetic_tum_dir
    for name in ('rgb.txt', 'depth.txt', 'groundtruth.txt', 'camera.yaml', 'SOURCE.md'):
        assert (path / name).is_file(), name
    rgb_lines = [ln.split() for ln in (path / 'rgb.txt').read_text().splitlines() if not ln.startswith('#')]
    assert len(rgb_lines) == 24 and all((path / f).is_file() for _, f in rgb_lines)
    assert len(list((path / 'depth').glob('*.png'))) == 24

    # Same config as the in-memory fixture: the files hold the same frames.
    frame = synthetic_sequence.frames[7]
    stamp, rgb_file = rgb_lines[7]
    assert float(stamp) == frame.stamp
    assert np.array_equal(cv2.cvtColor(cv2.imread(str(path / rgb_file)), cv2.COLOR_BGR2RGB), frame.rgb)
    raw = cv2.imread(str(path / 'depth' / f'{stamp}.png'), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert np.abs(png16_to_depth(raw) - frame.depth).max() <= 0.5 / DEPTH_SCALE + 1e-6

    gt = [ln.split() for ln in (path / 'groundtruth.txt').read_text().splitlines() if not ln.startswith('#')]
    values = np.array(gt[7][1:], dtype=float)
    assert np.allclose(values[:3], frame.pose[:3, 3], atol=1e-8)
    assert np.allclose(quat_to_matrix(values[3:]), frame.pose[:3, :3], atol=1e-8)

    calib = yaml.safe_load((path / 'camera.yaml').read_text())
    K = np.array(calib['camera_matrix']['data']).reshape(3, 3)
    assert (calib['image_width'], calib['image_height']) == (320, 240)
    assert np.allclose(K, synthetic_sequence.camera.K)
    assert calib['distortion_model'] == 'plumb_bob' and calib['distortion_coefficients']['data'] == [0.0] * 5
    assert 'depth-fusion synth' in (path / 'SOURCE.md').read_text()


def test_write_loads_with_tum_reader(synthetic_tum_dir, synthetic_sequence: Sequence):
    tum = pytest.importorskip('depth_fusion_ros.data.tum')
    seq = tum.load_tum_sequence(synthetic_tum_dir, width=320, height=240)
    assert len(seq) == 24 and seq.camera == synthetic_sequence.camera
    np.testing.assert_allclose(seq.stamps, synthetic_sequence.stamps, atol=1e-6)
    np.testing.assert_allclose(seq.poses, synthetic_sequence.poses, atol=1e-7)
    assert np.abs(seq.frames[3].depth - synthetic_sequence.frames[3].depth).max() < 1e-3


def test_writer_is_atomic_and_refuses_to_clobber(tmp_path):
    camera = PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5)
    poses = np.tile(np.eye(4), (2, 1, 1))
    rgb = np.zeros((6, 8, 3), np.uint8)
    depth = np.full((6, 8), 2.0, np.float32)
    depth[0, 0], depth[0, 1] = np.nan, 20.0  # invalid and beyond the uint16 range -> 0
    out = write_tum_folder(tmp_path / 'seq', camera, [1.0, 2.0], [rgb, rgb], [depth, depth], poses)
    raw = cv2.imread(str(out / 'depth' / '1.000000.png'), cv2.IMREAD_UNCHANGED)
    assert raw[0, 0] == 0 and raw[0, 1] == 0 and raw[1, 1] == 10000
    with pytest.raises(ValueError, match='already exists'):
        write_tum_folder(out, camera, [1.0, 2.0], [rgb, rgb], [depth, depth], poses)
    with pytest.raises(ValueError, match='only 1'):
        write_tum_folder(tmp_path / 'short', camera, [1.0, 2.0], [rgb], [depth], poses)
    with pytest.raises(ValueError, match='frame 0: rgb'):
        write_tum_folder(tmp_path / 'bad', camera, [1.0], [rgb[:, :4]], [depth], poses[:1])
    with pytest.raises(ValueError, match='strictly increasing'):
        write_tum_folder(tmp_path / 'bad', camera, [2.0, 1.0], [rgb, rgb], [depth, depth], poses)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['seq']  # no temp folders left behind
    write_tum_folder(out, camera, [3.0], [rgb], [depth], poses[:1], overwrite=True)
    assert (out / 'rgb' / '3.000000.png').is_file() and not (out / 'rgb' / '1.000000.png').exists()


def test_overwrite_replaces_a_sequence_and_never_a_folder_of_something_else(tmp_path, capsys):
    """`synth OUT --overwrite` replaced whatever OUT named: a mistyped output removed the
    user's files. Now only a folder depth-fusion wrote (or an empty one) is replaced: not a
    folder of other files, not a file, not a downloaded dataset in TUM layout."""
    from depth_fusion_ros.cli.main import main

    precious = tmp_path / 'thesis'
    precious.mkdir()
    (precious / 'chapter1.tex').write_text('months of work')
    dataset = tmp_path / 'rgbd_dataset_freiburg1_xyz'  # TUM layout, not written here
    dataset.mkdir()
    for name in ('rgb.txt', 'groundtruth.txt', 'depth.txt'):
        (dataset / name).write_text('# downloaded\n')
    args = ['--frames', '2', '--width', '64', '--height', '48', '--quiet', '--overwrite']
    for kept in (precious, dataset):
        assert main(['synth', str(kept), *args]) == 1
        err = capsys.readouterr().err
        assert 'is not a sequence depth-fusion wrote (no .written_by_depth_fusion_ros): refusing' in err
    assert (precious / 'chapter1.tex').read_text() == 'months of work'
    assert (dataset / 'rgb.txt').read_text() == '# downloaded\n'
    a_file = tmp_path / 'notes.txt'
    a_file.write_text('x')
    assert main(['synth', str(a_file), *args]) == 1
    assert 'is not a folder: refusing' in capsys.readouterr().err and a_file.read_text() == 'x'
    empty = tmp_path / 'empty'
    empty.mkdir()
    assert main(['synth', str(empty), *args]) == 0  # nothing in it to lose
    assert main(['synth', str(empty), *args, '--seed', '4']) == 0  # written here: replaced
    assert '--seed 4' in (empty / 'SOURCE.md').read_text()
    (empty / '.written_by_depth_fusion_ros').unlink()  # a synthetic folder from before the mark
    assert main(['synth', str(empty), *args, '--seed', '5']) == 0


def test_cli_synth(tmp_path, capsys):
    from depth_fusion_ros.cli.main import main

    out = tmp_path / 'cli'
    assert (
        main(
            ['synth', str(out), '--frames', '2', '--width', '64', '--height', '48', '--seed', '3', '--quiet']
        )
        == 0
    )
    assert len(list((out / 'rgb').glob('*.png'))) == 2
    assert '--seed 3' in (out / 'SOURCE.md').read_text()
    assert main(['synth', str(out), '--frames', '2', '--quiet']) == 1
    assert 'already exists' in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:  # argparse: usage + one-line error, exit 2
        main(['synth', str(tmp_path / 'x'), '--parallax', 'low', '--frames', '0', '--quiet'])
    assert exc.value.code == 2
    assert '--frames' in capsys.readouterr().err


def test_fixtures_have_their_parallax(
    synthetic_sequence: Sequence, synthetic_sequence_low_parallax: Sequence
):
    """The shared fixtures other stages use: same room and size, very different baselines."""
    high, low = synthetic_sequence, synthetic_sequence_low_parallax
    assert len(low) == len(high) and low.camera == high.camera
    step_high = np.linalg.norm(np.diff(high.poses[:, :3, 3], axis=0), axis=1)
    step_low = np.linalg.norm(np.diff(low.poses[:, :3, 3], axis=0), axis=1)
    assert step_high.mean() > 0.02  # >= 2 cm between consecutive frames
    assert step_low.mean() < 0.005
    assert not np.array_equal(low.frames[0].rgb, high.frames[0].rgb)


def test_time_offset_moves_the_told_poses_along_the_path():
    """``pose_time_offset``: each told pose is the camera's pose that much later (earlier when
    negative), at the velocity of its step; the images stay those of the true poses."""
    from scipy.spatial.transform import Rotation

    from depth_fusion_ros.data.synthetic.world import shifted_poses

    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    poses[:, 0, 3] = [0.0, 0.01, 0.02, 0.03]  # 1 cm per frame along x, turning 0.5 deg per frame
    poses[:, :3, :3] = Rotation.from_euler('y', [[0.0], [0.5], [1.0], [1.5]], degrees=True).as_matrix()
    for frames in (0.3, -0.3):
        moved = shifted_poses(poses, frames)
        np.testing.assert_allclose(moved[:, 0, 3], poses[:, 0, 3] + 0.01 * frames, atol=1e-12)
        yaw = Rotation.from_matrix(moved[:, :3, :3]).as_euler('xyz', degrees=True)[:, 1]
        np.testing.assert_allclose(yaw, [0.0, 0.5, 1.0, 1.5] + 0.5 * np.array(frames), atol=1e-9)
    np.testing.assert_array_equal(shifted_poses(poses, 0.0), poses)
    from depth_fusion_ros.geometry import interpolate_poses

    inside, valid = interpolate_poses(np.arange(4.0), poses, np.arange(4.0) + 0.3)  # the same, inside
    np.testing.assert_allclose(shifted_poses(poses, 0.3)[valid], inside[valid], atol=1e-12)

    cfg = SynthConfig(width=32, height=24, frames=3, pose_time_offset=0.01)  # 0.3 frame at 30 Hz
    late, exact = render_sequence(cfg), render_sequence(SynthConfig(width=32, height=24, frames=3))
    assert 'timeoffset+10ms' in late.name
    for a, b in zip(late.frames, exact.frames, strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
        assert (
            0
            < np.linalg.norm(a.pose[:3, 3] - b.pose[:3, 3])
            < np.linalg.norm(exact.frames[1].pose[:3, 3] - exact.frames[0].pose[:3, 3])
        )
    with pytest.raises(ValueError, match='pose_time_offset'):
        SynthConfig(pose_time_offset=0.05)  # more than one frame period at 30 Hz


def _synth_source(tmp_path, pose_frame: str) -> str:
    """SOURCE.md of a two-frame ``depth-fusion synth --pose-frame POSE_FRAME`` folder."""
    from depth_fusion_ros.cli.main import main

    out = tmp_path / pose_frame
    args = ['synth', str(out), '--frames', '2', '--width', '32', '--height', '24', '--quiet']
    assert main([*args, '--pose-frame', pose_frame]) == 0
    return (out / 'SOURCE.md').read_text()


def test_a_body_frames_poses_are_told_and_written_down(tmp_path):
    """``pose_frame: body``: the told poses are those of a REP 103 body frame holding the camera
    (``T_told = T_true @ M^-1``, the frame check's ``BODY_TO_OPTICAL``), the images and depth
    those of the camera; ``camera_from_pose_frame`` M turns them back; SOURCE.md and the CLI
    say so."""
    from depth_fusion_ros.geometry import BODY_TO_OPTICAL

    base = {'width': 32, 'height': 24, 'frames': 3, 'seed': 2}
    body = render_sequence(SynthConfig(**base, pose_frame='body'))
    optical = render_sequence(SynthConfig(**base))
    assert 'bodyposes' in body.name
    M = np.eye(4)
    M[:3, :3] = BODY_TO_OPTICAL
    for a, b in zip(body.frames, optical.frames, strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
        np.testing.assert_allclose(a.pose @ M, b.pose, atol=1e-12)
    with pytest.raises(ValueError, match='pose_frame'):
        SynthConfig(pose_frame='imu')
    text = _synth_source(tmp_path, 'body')
    assert '--pose-frame body' in text and "a body frame's poses" in text
    assert 'camera_from_pose_frame [0, 0, 0, -0.5, 0.5, -0.5, 0.5]' in text


def test_inverted_poses_are_told_and_written_down(tmp_path):
    """``pose_frame: inverted``: the told poses are the camera's inverted (T_cw, a SLAM's own),
    the images and depth the camera's; SOURCE.md says so and what reads them right."""

    base = {'width': 32, 'height': 24, 'frames': 3, 'seed': 2}
    inverted = render_sequence(SynthConfig(**base, pose_frame='inverted'))
    optical = render_sequence(SynthConfig(**base))
    assert 'invertedposes' in inverted.name
    for a, b in zip(inverted.frames, optical.frames, strict=True):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
        np.testing.assert_allclose(a.pose @ b.pose, np.eye(4), atol=1e-12)
    text = _synth_source(tmp_path, 'inverted')
    assert '--pose-frame inverted' in text and 'holds inverted poses' in text
    assert 'pose_inverted: true' in text


def test_a_pose_unit_scales_positions_and_depth_and_is_written_down(tmp_path):
    """``pose_scale``: positions and depth in a unit of 1 / pose_scale metres (a monocular
    SLAM's), the images rendered in metres; SOURCE.md and the CLI say so."""
    from depth_fusion_ros.cli.main import main

    base = {'width': 32, 'height': 24, 'frames': 3, 'seed': 2}
    scaled = render_sequence(SynthConfig(**base, pose_scale=0.3))
    metric = render_sequence(SynthConfig(**base))
    assert 'posescale0.3' in scaled.name
    for a, b in zip(scaled.frames, metric.frames, strict=True):
        assert np.array_equal(a.rgb, b.rgb)
        np.testing.assert_allclose(a.depth, 0.3 * b.depth, rtol=1e-6)
        np.testing.assert_allclose(a.pose[:3, 3], 0.3 * b.pose[:3, 3], atol=1e-12)
        np.testing.assert_array_equal(a.pose[:3, :3], b.pose[:3, :3])
    with pytest.raises(ValueError, match='pose_scale'):
        SynthConfig(pose_scale=2.0)
    out = tmp_path / 'unit'
    args = ['synth', str(out), '--frames', '2', '--width', '32', '--height', '24', '--quiet']
    assert main([*args, '--pose-scale', '0.5']) == 0
    text = (out / 'SOURCE.md').read_text()
    assert '--pose-scale 0.5' in text and 'unit of 2 m' in text


def test_cli_synth_time_offset_is_recorded(tmp_path):
    from depth_fusion_ros.cli.main import main

    out = tmp_path / 'late'
    args = ['synth', str(out), '--frames', '2', '--width', '32', '--height', '24', '--quiet']
    assert main([*args, '--pose-time-offset', '-0.02']) == 0
    text = (out / 'SOURCE.md').read_text()
    assert '--pose-time-offset -0.02' in text and 'out of sync' in text and '-20 ms' in text


def test_exposure_time_blurs_along_the_motion_and_keeps_the_stamps_depth():
    """``exposure_time``: each image is the mean of ``blur_samples`` views over the open
    shutter (the told pose and the depth stay the stamp's); 0 is the sharp image, bit for bit."""
    from depth_fusion_ros.data.synthetic import stress_config
    from depth_fusion_ros.data.synthetic.render import render_radiance
    from depth_fusion_ros.data.synthetic.world import exposure_poses

    sharp_cfg = SynthConfig(width=80, height=60, frames=3, sweep=0.12, noise_sigma=0.0)
    blur_cfg = SynthConfig(width=80, height=60, frames=3, sweep=0.12, noise_sigma=0.0, exposure_time=1 / 30)
    sharp, blurred = render_sequence(sharp_cfg), render_sequence(blur_cfg)
    assert 'blur33.3ms' in blurred.name and 'blur' not in sharp.name
    scene, trajectory = build_world(blur_cfg)
    views = exposure_poses(blur_cfg, trajectory.poses)
    assert views.shape == (3, 7, 4, 4) and exposure_poses(sharp_cfg, trajectory.poses) is None
    np.testing.assert_allclose(views[1, 3], trajectory.poses[1], atol=1e-12)  # centred on the stamp
    # Half a frame each way: the first and last views are halfway to the neighbouring frames.
    half = 0.5 * (trajectory.poses[2][:3, 3] - trajectory.poses[1][:3, 3])
    np.testing.assert_allclose(views[1, -1][:3, 3], trajectory.poses[1][:3, 3] + half, atol=1e-9)
    mean = np.mean([render_radiance(scene, blur_cfg.camera(), p)[0] for p in views[1]], axis=0)
    np.testing.assert_array_equal(blurred.frames[1].rgb, np.clip(np.rint(mean), 0, 255).astype(np.uint8))
    for a, b in zip(blurred.frames, sharp.frames, strict=True):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.pose, b.pose)
    # Blur smooths along the motion: less gradient energy than the sharp image of the same pose.
    grad = [np.abs(np.diff(f.frames[1].rgb.astype(np.float64), axis=1)).mean() for f in (blurred, sharp)]
    assert grad[0] < 0.9 * grad[1]
    assert stress_config('motion_blur').exposure_time == pytest.approx(1 / 30)
    with pytest.raises(ValueError, match='exposure_time'):
        SynthConfig(exposure_time=0.05)  # longer than a frame period at 30 Hz
    with pytest.raises(ValueError, match='blur_samples'):
        SynthConfig(blur_samples=1)


def test_gain_sigma_changes_each_frames_exposure_seeded():
    """``gain_sigma``: every frame scaled by its own seeded gain and clipped at 255 (an
    auto-exposure); the depth, the poses and the frame-to-frame draws do not depend on it."""
    from depth_fusion_ros.data.synthetic.world import frame_gain

    base = dict(width=48, height=36, frames=4, noise_sigma=0.0)
    flat, varied = render_sequence(SynthConfig(**base)), render_sequence(SynthConfig(**base, gain_sigma=0.2))
    assert 'gain0.2' in varied.name
    cfg = SynthConfig(**base, gain_sigma=0.2)
    gains = [frame_gain(cfg, i) for i in range(4)]
    assert len(set(gains)) == 4 and all(0.4 < g < 2.5 for g in gains)
    assert gains[2] == frame_gain(SynthConfig(**{**base, 'frames': 9}, gain_sigma=0.2), 2)
    for gain, a, b in zip(gains, varied.frames, flat.frames, strict=True):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.pose, b.pose)
        unclipped = (a.rgb < 255) & (b.rgb > 20)
        ratio = a.rgb[unclipped].astype(np.float64) / b.rgb[unclipped]
        assert np.median(ratio) == pytest.approx(gain, rel=0.03)
    assert frame_gain(SynthConfig(**base), 1) == 1.0
    with pytest.raises(ValueError, match='gain_sigma'):
        SynthConfig(gain_sigma=-0.1)


def test_cli_synth_sensor_stress_is_recorded(tmp_path):
    from depth_fusion_ros.cli.main import main

    out = tmp_path / 'blurred'
    args = ['synth', str(out), '--frames', '2', '--width', '32', '--height', '24', '--quiet']
    sensor = ['--exposure-time', '0.02', '--blur-samples', '3', '--walkers', '2', '--walker-speed', '0.5']
    sensor += ['--texture-period', '0.1']
    assert main([*args, '--stress', 'auto_exposure', *sensor]) == 0
    text = (out / 'SOURCE.md').read_text()
    assert '--exposure-time 0.02' in text and '--blur-samples 3' in text and '--gain-sigma 0.15' in text
    assert 'motion-blurred' in text and '20 ms exposure' in text and 'auto-exposure' in text
    assert '--walkers 2 --walker-speed 0.5' in text and 'not static' in text and '0.5 m/s' in text
    assert '--texture-period 0.1' in text and 'texture repeats' in text and '10 cm' in text


def test_walkers_move_across_the_view_and_leave_the_room_as_it_was():
    """``walkers``: a person-sized box walks back and forth across the view at
    ``walker_speed``; the depth shows it where it is at each frame, and the room around it
    (its furniture) is the room of the same seed without walkers."""
    from depth_fusion_ros.data.synthetic.walkers import WALKER_HALF, WALKER_REACH, walker_centres

    base = dict(width=64, height=48, frames=31, noise_sigma=0.0, sweep=0.3)
    cfg = SynthConfig(**base, walkers=1, walker_speed=1.2)
    scene, trajectory = build_world(cfg)
    still, _ = build_world(SynthConfig(**base))
    assert scene.names[-1] == 'walker0' and scene.n_objects == still.n_objects + 1
    np.testing.assert_array_equal(scene.centres[:-1], still.centres)  # the same furniture
    centres = np.array([walker_centres(cfg, trajectory, i)[0] for i in range(cfg.frames)])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert np.all(steps <= 1.2 / 30 + 1e-9) and np.median(steps) == pytest.approx(1.2 / 30)
    assert np.all(centres[:, 2] == WALKER_HALF[2])  # on the floor
    across = np.linalg.norm(centres[:, :2] - centres[:, :2].mean(axis=0), axis=1)
    assert across.max() <= WALKER_REACH + 1e-9
    moving, static = render_sequence(cfg), render_sequence(SynthConfig(**base))
    assert 'walkers1' in moving.name
    nearer = [(m.depth < s.depth - 1e-3).mean() for m, s in zip(moving.frames, static.frames, strict=True)]
    assert min(nearer) > 0 and np.median(nearer) > 0.1  # in front of the room, in view in every frame
    first = moving.frames[0].depth < static.frames[0].depth - 1e-3
    last = moving.frames[-1].depth < static.frames[-1].depth - 1e-3
    assert (first & last).sum() < 0.5 * first.sum()  # it has walked on
    with pytest.raises(ValueError, match='walkers'):
        SynthConfig(walkers=5)


def test_readout_time_exposes_each_row_at_its_own_pose():
    """``readout_time``: a rolling shutter. The top row is the view read first, the bottom row
    the view read last, the middle row the stamp's; the depth and pose stay the stamp's."""
    from depth_fusion_ros.data.synthetic import stress_config
    from depth_fusion_ros.data.synthetic.render import render_radiance
    from depth_fusion_ros.data.synthetic.world import exposure_poses, rolling_shutter_weights

    base = dict(width=64, height=49, frames=3, sweep=0.12, noise_sigma=0.0)
    cfg = SynthConfig(**base, readout_time=0.03)
    weights = rolling_shutter_weights(cfg)
    assert weights.shape == (49, 7) and rolling_shutter_weights(SynthConfig(**base)) is None
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    assert weights[0, 0] == pytest.approx(1.0) and weights[-1, -1] == pytest.approx(1.0)
    assert weights[24, 3] == pytest.approx(1.0)
    scene, trajectory = build_world(cfg)
    views = exposure_poses(cfg, trajectory.poses)[1]
    top = render_radiance(scene, cfg.camera(), views[0])[0]
    bottom = render_radiance(scene, cfg.camera(), views[-1])[0]
    skewed, sharp = render_sequence(cfg), render_sequence(SynthConfig(**base))
    assert 'rs30ms' in skewed.name
    rgb = skewed.frames[1].rgb
    # Rows are mixes in float32: equal to a grey level where a weight is a rounding off 1.
    near = dict(atol=1, rtol=0)
    np.testing.assert_allclose(rgb[0], np.clip(np.rint(top[0]), 0, 255), **near)
    np.testing.assert_allclose(rgb[-1], np.clip(np.rint(bottom[-1]), 0, 255), **near)
    np.testing.assert_allclose(rgb[24], sharp.frames[1].rgb[24], **near)  # the stamp's row
    assert not np.array_equal(rgb[0], sharp.frames[1].rgb[0])
    for a, b in zip(skewed.frames, sharp.frames, strict=True):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.pose, b.pose)
    assert stress_config('rolling_shutter').readout_time == pytest.approx(0.03)
    with pytest.raises(ValueError, match='readout_time'):
        SynthConfig(readout_time=0.05)


def test_texture_period_repeats_one_motif_on_every_textured_surface():
    """``texture_period``: every textured material is one motif repeated on a square lattice
    of about that period (tiles, bricks), so a patch one period along a surface looks like the
    patch itself; the geometry, the flat materials' share and the trajectory stay the seed's."""
    from depth_fusion_ros.data.synthetic import stress_config
    from depth_fusion_ros.data.synthetic.texture import PERIOD_TEXELS, periodic_albedo

    albedo = periodic_albedo(np.random.default_rng(1), 256)
    np.testing.assert_allclose(albedo, np.roll(albedo, PERIOD_TEXELS, axis=0), atol=1e-5)
    np.testing.assert_allclose(albedo, np.roll(albedo, PERIOD_TEXELS, axis=1), atol=1e-5)
    assert albedo.std() > 0.05 and np.abs(albedo - np.roll(albedo, PERIOD_TEXELS // 2, axis=1)).mean() > 0.03
    base = dict(width=64, height=48, frames=2, noise_sigma=0.0)
    tiled, plain = build_world(SynthConfig(**base, texture_period=0.1)), build_world(SynthConfig(**base))
    np.testing.assert_array_equal(tiled[0].centres, plain[0].centres)
    np.testing.assert_array_equal(tiled[1].poses, plain[1].poses)
    scene = tiled[0]
    periods = PERIOD_TEXELS / scene.surface_texels_per_m[scene.surface_texels_per_m != 1.0]
    assert periods.min() >= 0.1 * 0.8 - 1e-6 and periods.max() <= 0.1 * 1.25 + 1e-6
    seq = render_sequence(SynthConfig(**base, texture_period=0.1))
    assert 'period10cm' in seq.name
    assert np.array_equal(seq.frames[0].depth, render_sequence(SynthConfig(**base)).frames[0].depth)
    assert stress_config('repetitive').texture_period == pytest.approx(0.08)
    with pytest.raises(ValueError, match='texture_period'):
        SynthConfig(texture_period=0.01)


def test_a_shaking_hand_moves_every_pose_about_the_path_and_is_written_down(tmp_path):
    """``shake_m``, ``shake_deg``: 1-4 Hz sinusoids of about that standard deviation per camera
    axis on the same path in the same room (true and told poses alike), seeded; SOURCE.md says so."""
    from depth_fusion_ros.data.synthetic import write_synthetic_sequence
    from depth_fusion_ros.data.synthetic.world import build_world
    from depth_fusion_ros.geometry import relative_pose, rotation_angle

    base = {'width': 32, 'height': 24, 'frames': 90, 'seed': 4, 'parallax': 'high'}
    steady_scene, steady = build_world(SynthConfig(**base))
    shaken_scene, shaken = build_world(SynthConfig(**base, shake_m=0.005, shake_deg=0.5))
    assert np.array_equal(shaken_scene.centres, steady_scene.centres)  # the same room
    moves = [relative_pose(a, b) for a, b in zip(steady.poses, shaken.poses, strict=True)]
    offsets = np.stack([m[:3, 3] for m in moves])
    angles = np.degrees([rotation_angle(m[:3, :3]) for m in moves])
    assert 0.003 < float(offsets.std(axis=0).mean()) < 0.008  # 5 mm per axis, give or take the draw
    assert 0.4 < float(np.sqrt(np.mean(angles**2)) / np.sqrt(3)) < 1.0  # 0.5 deg per axis
    again = build_world(SynthConfig(**base, shake_m=0.005, shake_deg=0.5))[1]
    assert np.array_equal(again.poses, shaken.poses)
    cfg = SynthConfig(**{**base, 'frames': 3}, shake_m=0.005, shake_deg=0.5)
    text = (write_synthetic_sequence(tmp_path / 'shaky', cfg) / 'SOURCE.md').read_text()
    assert 'The hand shakes' in text and '_shake5mm0.5deg' in text
    with pytest.raises(ValueError, match='shake'):
        SynthConfig(shake_deg=10.0)


def test_a_pose_source_out_of_sync_is_recorded_as_it_would_stamp(tmp_path):
    """``pose_time_offset``: groundtruth.txt holds each frame's pose stamped that much before
    its image (``world.pose_source``); read at the image stamps it gives the told poses, and the
    loaders keep it as ``Sequence.pose_stream`` (a TUM folder, and a bag made from it)."""
    from depth_fusion_ros.data.rosbag_convert import convert
    from depth_fusion_ros.data.rosbag_read import load_bag_sequence
    from depth_fusion_ros.data.synthetic import write_synthetic_sequence
    from depth_fusion_ros.data.tum import load_tum_sequence

    cfg = SynthConfig(width=32, height=24, frames=4, pose_time_offset=0.02, shake_deg=0.5)
    memory = render_sequence(cfg)
    stamps, poses = memory.pose_stream
    np.testing.assert_allclose(stamps, [*(memory.stamps - 0.02), memory.stamps[-1]])
    exact = render_sequence(SynthConfig(width=32, height=24, frames=4, shake_deg=0.5))
    np.testing.assert_allclose(poses[:-1], exact.poses)  # the samples are the true poses
    folder = write_synthetic_sequence(tmp_path / 'late', cfg)
    loaded = load_tum_sequence(folder, width=32, height=24)
    assert len(loaded) == 4 and loaded.dropped.get('outside_groundtruth', 0) == 0
    np.testing.assert_allclose(loaded.pose_stream[0], stamps, atol=1e-6)
    # Read at the image stamps (groundtruth.txt keeps microseconds: 3 um at these 10 m/s).
    np.testing.assert_allclose(loaded.poses, memory.poses, atol=1e-5)
    convert(folder, tmp_path / 'bag')
    bag = load_bag_sequence(tmp_path / 'bag', 32, 24)
    # The bag carries the pose source's own samples (20 ms before the images), not blends at them.
    assert bag.pose_stream is not None and len(bag.pose_stream[0]) == len(stamps) == len(bag) + 1
    np.testing.assert_array_equal(bag.pose_stream[0], loaded.pose_stream[0])
    np.testing.assert_allclose(bag.pose_stream[1], loaded.pose_stream[1], atol=1e-9)
    np.testing.assert_allclose(bag.poses, loaded.poses, atol=1e-9)


def test_the_keyframe_stream_moves_one_step_every_frame_back_and_forth():
    """The ``keyframes`` stress stream is a SLAM's keyframe stream: every frame 0.15 m and 6.7 deg
    from the last, sweeping back and forth. (Its wave used to jump 2h + 1 steps back every 4h
    frames: a 60 deg, 1.3 m teleport, a relocalisation rather than the stream it names.)"""
    from depth_fusion_ros.data.synthetic import build_world, stress_config

    _, trajectory = build_world(stress_config('keyframes', frames=100, seed=21))
    poses = trajectory.poses
    steps = [relative_pose(poses[i - 1], poses[i]) for i in range(1, len(poses))]
    moved = np.array([np.linalg.norm(T[:3, 3]) for T in steps])
    turned = np.degrees([rotation_angle(T[:3, :3]) for T in steps])
    np.testing.assert_allclose(moved, 0.15, rtol=1e-6)
    np.testing.assert_allclose(turned, 6.7, rtol=1e-4)
    # back and forth: it comes back to where it started every 20 frames
    np.testing.assert_allclose(poses[20], poses[0], atol=1e-9)
    assert np.linalg.norm(poses[5][:3, 3] - poses[0][:3, 3]) > 0.6  # five steps along the arc


def test_a_distorted_lens_is_rendered_through_and_not_written_down(tmp_path):
    """``lens_k1``: images and depth are seen through a radial distortion that camera.yaml does
    not hold. Undistorting them with OpenCV's own model (plumb_bob, the same k1) gives back the
    pinhole render: the rays are bent as OpenCV would bend them, and depth stays z-depth."""
    from depth_fusion_ros.cli.main import main
    from depth_fusion_ros.radial_lens import undistort_radial

    cfg = SynthConfig(width=160, height=120, frames=1, seed=4, parallax='high', boxes=8)
    lens = SynthConfig(width=160, height=120, frames=1, seed=4, parallax='high', boxes=8, lens_k1=-0.2)
    pinhole, bent = render_sequence(cfg), render_sequence(lens)
    assert bent.camera == pinhole.camera == bent.gt_camera  # the pipeline is told a pinhole
    cam = bent.gt_camera
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    D = np.array([-0.2, 0.0, 0.0, 0.0])
    inner = (slice(8, -8), slice(8, -8))
    moved = np.abs(bent.frames[0].depth - pinhole.frames[0].depth) / pinhole.frames[0].depth
    back = cv2.undistort(bent.frames[0].depth, K, D) / pinhole.frames[0].depth - 1.0
    assert np.median(moved[inner]) > 20 * np.median(np.abs(back[inner]))
    assert np.median(np.abs(back[inner])) < 1e-4
    grey = np.abs(cv2.undistort(bent.frames[0].rgb, K, D).astype(float) - pinhole.frames[0].rgb)
    apart = np.abs(bent.frames[0].rgb.astype(float) - pinhole.frames[0].rgb)
    assert grey[inner].mean() < 0.5 * apart[inner].mean()
    # The slopes invert OpenCV's distortion exactly, and a column of k1 undoes each on its own.
    x, y = undistort_radial(np.array([0.5, -0.3, 0.0]), np.array([0.4, 0.2, 0.0]), -0.2)
    r2 = x * x + y * y
    assert np.allclose(x * (1 - 0.2 * r2), [0.5, -0.3, 0.0], atol=1e-12)
    assert np.allclose(y * (1 - 0.2 * r2), [0.4, 0.2, 0.0], atol=1e-12)
    xs, _ = undistort_radial(np.array([0.5, -0.3, 0.0]), np.array([0.4, 0.2, 0.0]), np.array([[-0.2], [0.0]]))
    assert np.array_equal(xs[0], x) and np.array_equal(xs[1], [0.5, -0.3, 0.0])
    with pytest.raises(ValueError, match='lens_k1'):
        SynthConfig(lens_k1=0.5)
    out = tmp_path / 'lens'
    args = ['synth', str(out), '--frames', '1', '--width', '32', '--height', '24', '--lens-k1', '-0.1']
    assert main([*args, '--quiet']) == 0
    text = (out / 'SOURCE.md').read_text()
    assert '--lens-k1 -0.1' in text and 'does not say so' in text and 'k1 = -0.1' in text
    assert yaml.safe_load((out / 'camera.yaml').read_text()).get('D', [0.0])[0] == 0.0
