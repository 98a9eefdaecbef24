"""Rigid-body poses: quaternions, 4x4 transforms, validation and interpolation (no ROS).

Conventions used everywhere in the package:

* a pose ``T_wc`` is a 4x4 float64 camera-to-world transform (the pose of the optical
  frame in the map frame, REP 103/105): ``X_w = T_wc @ X_c``;
* quaternions are ``(x, y, z, w)``, the order of ``geometry_msgs/Quaternion`` and the TUM
  ground-truth files;
* the relative transform used by the multi-view search is ``T_ok = inv(T_wo) @ T_wk``: it
  maps keyframe-camera points into the other camera.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

# scipy.spatial is imported where it is used (matrix_to_quat, interpolate_poses): importing it
# costs about 0.3 s of CPU, and every node process imports this module before it can say
# ready (issue 13's time to ready); quat_to_matrix, on every pose message, is plain numpy.
# A node that will call them on its stream loads it once before "ready": load_rotations.

#: Tolerance on ``R^T R - I`` (max abs) above which a rotation is rejected as not orthonormal.
ORTHONORMAL_TOL = 1e-3
#: Tolerance on ``| |q| - 1 |`` above which a quaternion is called not normalised.
QUAT_NORM_TOL = 1e-3


def load_rotations() -> None:
    """Import what :func:`matrix_to_quat` and :func:`interpolate_poses` use, now: a node that
    calls them on every posed frame does it before it says "ready", so the ~0.25 s import does
    not stall its callbacks on the stream's first frame (py-spy of a flat-out run,
    docs/performance.md)."""
    import scipy.spatial.transform  # noqa: F401


class PoseError(ValueError):
    """A pose or quaternion that cannot be used (NaN, zero norm, not a rotation)."""


def quat_to_matrix(q_xyzw: np.ndarray, *, normalise: bool = True) -> np.ndarray:
    """Rotation matrix of an ``(x, y, z, w)`` quaternion.

    With ``normalise=False`` a quaternion whose norm is off by more than ``QUAT_NORM_TOL``
    raises, which is what a node wants for incoming messages (a SLAM that publishes
    non-unit quaternions is broken, and silently fixing it hides the bug).
    """
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(4)
    if not np.all(np.isfinite(q)):
        raise PoseError(f'quaternion has non-finite values: {q.tolist()}')
    norm = float(np.linalg.norm(q))
    if norm < 1e-9:
        raise PoseError('quaternion has zero norm')
    if not normalise and abs(norm - 1.0) > QUAT_NORM_TOL:
        raise PoseError(f'quaternion is not normalised (|q| = {norm:.6f})')
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """``(x, y, z, w)`` quaternion of a rotation matrix, with ``w >= 0``."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return q if q[3] >= 0 else -q


def make_pose(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 transform from a translation and an ``(x, y, z, w)`` quaternion."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q_xyzw)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(T)):
        raise PoseError(f'translation has non-finite values: {np.asarray(t).tolist()}')
    return T


def pose_to_tq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 4x4 transform into ``(t (3,), q_xyzw (4,))``."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), matrix_to_quat(T[:3, :3])


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (cheaper and exacter than ``np.linalg.inv``)."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def relative_pose(T_wk: np.ndarray, T_wo: np.ndarray) -> np.ndarray:
    """``T_ok = inv(T_wo) @ T_wk``: keyframe-camera coordinates to other-camera coordinates."""
    return invert_pose(T_wo) @ T_wk


def validate_pose(T: np.ndarray, what: str = 'pose') -> np.ndarray:
    """Return ``T`` as float64 4x4 or raise ``PoseError`` saying what is wrong with it."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise PoseError(f'{what}: expected a 4x4 matrix, got shape {T.shape}')
    return validate_poses(T[None], [what])[0]


def validate_poses(T: np.ndarray, what: Sequence[str]) -> np.ndarray:
    """``validate_pose`` of a stack of poses (K, 4, 4) in one batch, ``what[k]`` naming pose k
    in the error: the first bad one raises. One set of checks for one pose or a window of them
    (neighbour selection asks for 30 per keyframe)."""
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise PoseError(f'poses: expected (K, 4, 4) matrices, got shape {T.shape}')
    finite = np.isfinite(T).all(axis=(1, 2))
    R = np.where(finite[:, None, None], T[:, :3, :3], np.eye(3))  # checked only where finite
    last_row = np.abs(T[:, 3] - (0.0, 0.0, 0.0, 1.0)).max(axis=1) <= 1e-9
    err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    proper = (err <= ORTHONORMAL_TOL) & (np.linalg.det(R) > 0)
    bad = np.flatnonzero(~(finite & last_row & proper))
    if bad.size:
        k = int(bad[0])
        if not finite[k]:
            raise PoseError(f'{what[k]}: contains NaN or infinite values')
        if not last_row[k]:
            raise PoseError(f'{what[k]}: last row is {T[k, 3].tolist()}, expected [0, 0, 0, 1]')
        raise PoseError(f'{what[k]}: rotation is not orthonormal (max |R^T R - I| = {err[k]:.2e})')
    return T


#: The camera's optical frame (x right, y down, z forward) in a REP 103 body frame (x forward,
#: y left, z up), as a rotation: ``T_wc = T_body @ M``, the ``camera_from_pose_frame``
#: [0, 0, 0, -0.5, 0.5, -0.5, 0.5]. The frame check's usual turn (multiview/frame_fit.py) and
#: the synthetic body-frame poses (data/synthetic, ``pose_frame``).
BODY_TO_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
BODY_TO_OPTICAL.setflags(write=False)


def skews(t: np.ndarray) -> np.ndarray:
    """(S, 3, 3) cross-product matrices of vectors ``t`` (S, 3)."""
    out = np.zeros((len(t), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    return out - np.transpose(out, (0, 2, 1))


def rotation_matrices(rotvecs: np.ndarray) -> np.ndarray:
    """(S, 3, 3) rotations of rotation vectors (S, 3) (radians). scipy is imported here, at the
    first call: scipy.spatial costs a node process ~0.3 s of CPU, which its start-up must not
    pay (issue 13; the mount check and the pose refinement call this)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rotvecs, dtype=np.float64).reshape(-1, 3)).as_matrix()


def rotation_angle(R: np.ndarray) -> float:
    """Angle (radians) of a rotation matrix."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def interpolate_poses(
    stamps: np.ndarray, poses: np.ndarray, query: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate poses at ``query`` stamps: linear translation, slerp rotation.

    ``stamps`` (N,) must be strictly increasing, ``poses`` (N, 4, 4). Returns
    ``(T (M, 4, 4), valid (M,))``; a query outside ``[stamps[0], stamps[-1]]`` is invalid
    (its pose is NaN) because extrapolating a trajectory invents motion.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    query = np.atleast_1d(np.asarray(query, dtype=np.float64))
    if stamps.ndim != 1 or poses.shape != (len(stamps), 4, 4):
        raise ValueError(f'stamps {stamps.shape} and poses {poses.shape} do not match')
    if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
        raise ValueError('pose stamps must be strictly increasing')
    out = np.full((len(query), 4, 4), np.nan)
    if len(stamps) == 0:
        return out, np.zeros(len(query), dtype=bool)
    valid = (query >= stamps[0]) & (query <= stamps[-1])
    if not np.any(valid):
        return out, valid
    q = query[valid]
    if len(stamps) == 1:
        out[valid] = poses[0]
        return out, valid
    idx = np.clip(np.searchsorted(stamps, q, side='right') - 1, 0, len(stamps) - 2)
    alpha = (q - stamps[idx]) / (stamps[idx + 1] - stamps[idx])
    t = poses[idx, :3, 3] * (1 - alpha)[:, None] + poses[idx + 1, :3, 3] * alpha[:, None]
    from scipy.spatial.transform import Rotation, Slerp

    rots = Rotation.from_matrix(poses[:, :3, :3])
    R = Slerp(stamps, rots)(q).as_matrix()
    T = np.tile(np.eye(4), (len(q), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    out[valid] = T
    return out, valid


def interpolate_pose(stamps: np.ndarray, poses: np.ndarray, t: float) -> np.ndarray | None:
    """Single-stamp convenience wrapper of :func:`interpolate_poses` (``None`` if uncovered)."""
    T, valid = interpolate_poses(stamps, poses, np.array([t]))
    return T[0] if valid[0] else None


def transform_from_parameter(values: list[float], name: str = 'camera_from_pose_frame') -> np.ndarray:
    """4x4 of ``[x, y, z, qx, qy, qz, qw]``; ``ValueError`` naming the parameter if it is not rigid."""
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (7,) or not np.all(np.isfinite(v)):
        raise ValueError(
            f'parameter {name!r} must be 7 finite numbers [x, y, z, qx, qy, qz, qw], got {values}'
        )
    norm = float(np.linalg.norm(v[3:]))
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(
            f'parameter {name!r}: quaternion (qx, qy, qz, qw) = {v[3:].tolist()} has norm {norm:.4g}, '
            'expected 1 (order is x, y, z, w as tf2_echo prints it)'
        )
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(v[3:] / norm)
    T[:3, 3] = v[:3]
    return T
