"""The epipolar cost the calibration checks fit (focal length, time offset, mount): how far
matched features lie from the epipolar lines of a told relative pose.

A told pose's error moves every match of a pair alike, so the checks compare costs of whole
pairs under candidate poses or cameras; the soft-L1 loss keeps a few wrong matches from
deciding. Everything is batched over the candidates: one pass per pair.
"""

from __future__ import annotations

import numpy as np

from ..geometry import skews

#: Sampson distance (px) where the soft-L1 loss turns from squares to absolute values.
_LOSS_SCALE_PX = 0.5


def skew(t: np.ndarray) -> np.ndarray:
    """The cross-product matrix of a 3-vector."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_distances(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (px) of matches ``p1 -> p2`` (N, 2) under fundamental matrix
    ``F`` (3, 3): (N,); or under each of S matrices (S, 3, 3): (S, N)."""
    if F.ndim == 2:
        return _signed_sampson(F[None], p1, p2)[0]
    return _signed_sampson(F, p1, p2)


def scaled_fundamentals(scales: np.ndarray, K: np.ndarray, T_ba: np.ndarray) -> np.ndarray:
    """(S, 3, 3) fundamental matrices of the relative pose ``T_ba`` of a camera ``K`` with its
    focal lengths scaled by each of ``scales`` (principal point kept)."""
    Ks = np.repeat(K[None].astype(np.float64), len(scales), axis=0)
    Ks[:, 0, 0] *= scales
    Ks[:, 1, 1] *= scales
    Ki = np.linalg.inv(Ks)
    E = skew(T_ba[:3, 3]) @ T_ba[:3, :3]
    return np.transpose(Ki, (0, 2, 1)) @ E @ Ki


def _signed_sampson(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances (S, N) of matches ``p1 -> p2`` (N, 2) under each of S
    fundamental matrices ``F`` (S, 3, 3); or of matches of their own per candidate, ``p1``,
    ``p2`` (S, N, 2) (the same matches with each candidate's lens distortion undone)."""
    return _entries_sampson(np.moveaxis(F, (1, 2), (0, 1))[..., None], p1, p2)


def _entries_sampson(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Signed Sampson distances of matches ``p1 -> p2`` (..., N, 2) under fundamental matrices
    given entry by entry, ``f`` (3, 3, ...) (each entry broadcasting against the matches: (S, 1)
    for one matrix per candidate, (S, N) for one per candidate and match).

    Written out per component (the last coordinate is 1) rather than as ``einsum`` over the
    3-vectors: numpy's einsum loops over a dimension of 3 for every (S, N) element, the
    component form is a dozen whole-array multiply-adds, 4x faster (1.6 against 6.5 ms for
    101 poses x 620 matches, a time offset check's pair) and the same to 1e-12."""
    x, y = p1[..., 0], p1[..., 1]
    u, v = p2[..., 0], p2[..., 1]
    fx1 = f[0, 0] * x + f[0, 1] * y + f[0, 2]  # F x1, rows 0-2
    fy1 = f[1, 0] * x + f[1, 1] * y + f[1, 2]
    fz1 = f[2, 0] * x + f[2, 1] * y + f[2, 2]
    gx2 = f[0, 0] * u + f[1, 0] * v + f[2, 0]  # F^T x2, rows 0-1
    gy2 = f[0, 1] * u + f[1, 1] * v + f[2, 1]
    norm = np.sqrt(fx1 * fx1 + fy1 * fy1 + gx2 * gx2 + gy2 * gy2)
    return (u * fx1 + v * fy1 + fz1) / np.maximum(norm, 1e-12)


def _soft_l1(distances: np.ndarray) -> np.ndarray:
    """Squares under ``_LOSS_SCALE_PX``, absolute values beyond."""
    r = distances / _LOSS_SCALE_PX
    return np.sqrt(1.0 + r * r) - 1.0


def soft_l1_sampson(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Soft-L1 costs (S, N) of the Sampson distances of matches ``p1 -> p2`` (N, 2, or (S, N, 2):
    :func:`_signed_sampson`) under each of S fundamental matrices ``F`` (S, 3, 3), in one pass:
    squares under ``_LOSS_SCALE_PX``, absolute values beyond. Every calibration check fits its
    parameter with it."""
    return _soft_l1(_signed_sampson(F, p1, p2))


def soft_l1_sampson_entries(f: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """:func:`soft_l1_sampson` of matches ``p1 -> p2`` (N, 2) each under a matrix of its own per
    candidate, given entry by entry: ``f`` (3, 3, S, N) (the stacked pairs of ``pair_stack.py``,
    each match under its own pair's matrix: contiguous per entry, as the arithmetic reads it)."""
    return _soft_l1(_entries_sampson(f, p1, p2))


def pose_costs(K: np.ndarray, T_ba: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Mean soft-L1 Sampson cost (S,) of matches ``p1 -> p2`` under each of S relative poses
    ``T_ba`` (S, 4, 4; first-camera to second-camera coordinates) of a camera ``K``; ``inf``
    where a pose does not move (no epipolar geometry)."""
    Ki = np.linalg.inv(K)
    t = T_ba[:, :3, 3]
    moving = np.linalg.norm(t, axis=1) >= 1e-5
    F = Ki.T @ skews(t) @ T_ba[:, :3, :3] @ Ki
    costs = np.full(len(T_ba), np.inf)
    costs[moving] = soft_l1_sampson(F[moving], p1, p2).mean(axis=1)
    return costs
