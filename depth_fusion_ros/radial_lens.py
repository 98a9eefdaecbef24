"""Undoing a radial lens distortion (plumb_bob ``k1``) in normalised image coordinates.

Two places need it: the synthetic renderer, which casts each pixel's ray through a distorted
lens (``data/synthetic/render.py``), and the focal check's lens fit, which undoes candidate
distortions of its matches (``multiview/lens_fit.py``). OpenCV's ``undistortPoints`` does the
same for one set of coefficients at a time; here ``k1`` broadcasts, so a whole grid of
candidates is undone in one pass.
"""

from __future__ import annotations

import numpy as np

#: Stop when no coordinate moves by more than this (normalised units).
TOLERANCE = 1e-12
#: At most this many steps (the iteration contracts by ``|3 k1 r^2|`` per step).
MAX_STEPS = 100


def undistort_radial(xd: np.ndarray, yd: np.ndarray, k1: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates ``(x, y)`` of distorted ones ``(xd, yd)`` under
    ``xd = x (1 + k1 r^2)``, ``r^2 = x^2 + y^2`` (OpenCV's plumb_bob with only ``k1``), in float64.

    ``k1`` broadcasts against the coordinates (a column of candidates against a row of points
    gives one row per candidate). The fixed-point iteration ``x = xd / (1 + k1 r^2)``, as
    ``cv2.undistortPoints``, runs until it moves no coordinate by :data:`TOLERANCE`; it
    contracts wherever ``|3 k1 r^2| < 1``.
    """
    xd, yd = np.asarray(xd, dtype=np.float64), np.asarray(yd, dtype=np.float64)
    k1 = np.asarray(k1, dtype=np.float64)
    shape = np.broadcast_shapes(xd.shape, yd.shape, k1.shape)
    x, y = np.broadcast_to(xd, shape).copy(), np.broadcast_to(yd, shape).copy()
    if not np.any(k1):
        return x, y
    for _ in range(MAX_STEPS):
        scale = 1.0 + k1 * (x * x + y * y)
        nx, ny = xd / scale, yd / scale
        step = max(float(np.max(np.abs(nx - x), initial=0.0)), float(np.max(np.abs(ny - y), initial=0.0)))
        x, y = nx, ny
        if step < TOLERANCE:
            break
    return x, y
