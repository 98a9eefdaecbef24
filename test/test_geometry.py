"""Poses, quaternions, interpolation and the pose buffer."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.geometry import (
    PoseError,
    interpolate_pose,
    interpolate_poses,
    invert_pose,
    make_pose,
    matrix_to_quat,
    pose_to_tq,
    quat_to_matrix,
    relative_pose,
    validate_pose,
    validate_poses,
)
from depth_fusion_ros.pose_buffer import PoseBuffer


def random_pose(rng):
    return make_pose(rng.normal(size=3), Rotation.random(random_state=rng).as_quat())


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = Rotation.random(random_state=rng).as_quat()
        q = q if q[3] >= 0 else -q
        assert np.allclose(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12)


def test_quat_to_matrix_matches_scipy_for_unnormalised_quaternions():
    # quat_to_matrix is plain numpy (no scipy import on the nodes' start path): same matrices
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.normal(size=4) * rng.uniform(0.1, 3.0)
        expected = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
        assert np.allclose(quat_to_matrix(q), expected, atol=1e-12)


def test_node_modules_start_without_scipy():
    # scipy.spatial costs ~0.3 s of CPU per node process before it can say ready (issue 13)
    import subprocess
    import sys

    code = (
        'import sys; import depth_fusion_ros.nodes.fusion_node, depth_fusion_ros.nodes.multi_view_node; '
        'print("scipy.spatial" in sys.modules)'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == 'False'


def test_bad_quaternions_raise():
    with pytest.raises(PoseError, match='non-finite'):
        quat_to_matrix([np.nan, 0, 0, 1])
    with pytest.raises(PoseError, match='zero norm'):
        quat_to_matrix([0, 0, 0, 0])
    with pytest.raises(PoseError, match='not normalised'):
        quat_to_matrix([0, 0, 0, 2], normalise=False)


def test_pose_inverse_and_relative():
    rng = np.random.default_rng(1)
    T_wk, T_wo = random_pose(rng), random_pose(rng)
    assert np.allclose(invert_pose(T_wk) @ T_wk, np.eye(4), atol=1e-12)
    X_k = np.array([0.3, -0.2, 2.0, 1.0])
    assert np.allclose(relative_pose(T_wk, T_wo) @ X_k, np.linalg.inv(T_wo) @ T_wk @ X_k)
    t, q = pose_to_tq(T_wk)
    assert np.allclose(make_pose(t, q), T_wk, atol=1e-12)


def test_validate_pose_rejects_nan_and_shear():
    T = np.eye(4)
    T[0, 0] = np.nan
    with pytest.raises(PoseError, match='NaN'):
        validate_pose(T)
    S = np.eye(4)
    S[0, 1] = 0.2
    with pytest.raises(PoseError, match='orthonormal'):
        validate_pose(S)


def test_a_stack_of_poses_names_its_first_bad_one():
    """``validate_poses`` checks a window at once, as ``validate_pose`` checks one."""
    poses = np.tile(np.eye(4), (4, 1, 1))
    assert np.array_equal(validate_poses(poses, ['a', 'b', 'c', 'd']), poses)
    poses[2, 3] = (0.0, 0.0, 1.0, 1.0)
    poses[3, 0, 0] = np.inf
    with pytest.raises(PoseError, match=r'^c: last row'):
        validate_poses(poses, ['a', 'b', 'c', 'd'])
    poses[1, :3, :3] = -np.eye(3)  # orthonormal, but a reflection
    with pytest.raises(PoseError, match=r'^b: rotation is not orthonormal'):
        validate_poses(poses, ['a', 'b', 'c', 'd'])


def test_interpolation_midpoint_and_span():
    T0 = make_pose([0, 0, 0], Rotation.from_euler('z', 0).as_quat())
    T1 = make_pose([2, 0, 0], Rotation.from_euler('z', 90, degrees=True).as_quat())
    Tm = interpolate_pose(np.array([0.0, 1.0]), np.stack([T0, T1]), 0.5)
    assert np.allclose(Tm[:3, 3], [1, 0, 0])
    assert np.isclose(Rotation.from_matrix(Tm[:3, :3]).as_euler('zyx', degrees=True)[0], 45)
    _, valid = interpolate_poses(np.array([0.0, 1.0]), np.stack([T0, T1]), np.array([-0.1, 0, 1, 1.1]))
    assert valid.tolist() == [False, True, True, False]


def test_pose_buffer_out_of_order_gap_and_capacity():
    buf = PoseBuffer(capacity=4, max_gap=0.5)
    for t in (0.2, 0.0, 0.1):  # out of order
        buf.insert(t, make_pose([t, 0, 0], [0, 0, 0, 1]))
    assert np.allclose(buf.lookup(0.15).pose[:3, 3], [0.15, 0, 0])
    assert buf.lookup(0.3).pose is None and 'newer' in buf.lookup(0.3).reason
    buf.insert(1.5, make_pose([1.5, 0, 0], [0, 0, 0, 1]))
    assert 'gap' in buf.lookup(1.0).reason
    buf.insert(1.6, make_pose([1.6, 0, 0], [0, 0, 0, 1]))
    assert len(buf) == 4 and buf.span == (0.1, 1.6)
    with pytest.raises(PoseError):
        buf.insert(2.0, np.full((4, 4), np.nan))


def test_camera_scaling_matches_resize_convention():
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    half = cam.scaled(320, 240)
    assert (half.fx, half.cx, half.cy) == (262.5, 159.5, 119.5)
    depth = np.full((240, 320), 2.0)
    pts = half.backproject(depth)
    uv, z = half.project(pts)
    u, v = half.pixel_grid()
    assert np.allclose(uv[..., 0], u) and np.allclose(uv[..., 1], v) and np.allclose(z, 2.0)


def test_strided_backprojection_is_the_full_one_sliced():
    """The fusion node's cloud backprojects every 2nd pixel only; the points must be the
    ones the full image would give at those pixels, bit for bit, also where H or W is not a
    multiple of the stride."""
    cam = PinholeCamera(321, 239, 260.0, 262.0, 160.3, 119.7)
    depth = np.random.default_rng(0).uniform(0.5, 4.0, (239, 321)).astype(np.float32)
    full = cam.backproject(depth)
    for stride in (1, 2, 3, 7):
        assert np.array_equal(cam.backproject(depth, stride), full[::stride, ::stride])
    with pytest.raises(ValueError, match='stride'):
        cam.backproject(depth, 0)


def test_scipy_rotations_load_only_when_asked():
    """Importing geometry leaves scipy.spatial out (a node's time to ready); load_rotations
    brings it in, as multi_view_node does before it says ready."""
    import subprocess
    import sys

    code = (
        'import sys; import depth_fusion_ros.geometry as g; '
        "a = 'scipy.spatial.transform' in sys.modules; g.load_rotations(); "
        "print(a, 'scipy.spatial.transform' in sys.modules)"
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ['False', 'True']
