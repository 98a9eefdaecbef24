"""One frame's epipolar geometry for every pixel of the filter's keyframe, in a handful of ops.

What the per-pixel tests (``filter_frame_update.choose_rows``) and the searches read: the rows'
projections at infinity, the epipolar motion per unit inverse depth, the gradient along the
epipolar line and the visibility, all from one homography product per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..camera import PinholeCamera
from .cost_volume import epipolar_motion
from .filter_keyframe import FilterKeyframe


@dataclass
class FrameGeometry:
    """One frame's epipolar geometry for every keyframe pixel, at the pixel's prior mean."""

    a: torch.Tensor  # (3, M) K R_fk x_n, coordinate-first: the projection at inverse depth rho is a + rho b
    b: tuple[float, float, float]  # K t_fk's float32 values as numbers (operands without selects)
    j: torch.Tensor  # (M,) epipolar motion (px per unit inverse depth) at the prior mean
    along: torch.Tensor  # (M,) |grey gradient . unit epipolar direction|
    visible: torch.Tensor  # (M,) bool: the prior mean projects in front, inside the matching margin


def frame_geometry(
    key: FilterKeyframe, camera: PinholeCamera, T_fk: np.ndarray, margin: float
) -> FrameGeometry:
    """``EpipolarRays`` of one frame, its ``project`` and ``motion`` at the prior means, fused.

    With ``w = a_2 + rho b_2``: ``u = (a_0 + rho b_0) / w`` and ``du/drho = (b_0 a_2 - a_0 b_2) / w^2``;
    the numerators of the motion do not depend on ``rho``, so the epipolar direction (the
    gradient test) costs two products per pixel, and everything is a handful of (M,) ops.
    ``a`` is coordinate-first (3, M): each coordinate is then a contiguous row, so every op
    below runs vectorised over the pixels (pixel-first, the columns were strided: the same
    numbers at about twice the cost), and the searches gather their rows with one
    ``index_select`` straight into the layout ``grid`` takes.
    """
    h, (b0, b1, b2) = frame_projection(camera, T_fk, key.us.device)
    # H (u, v, 1), one row per coordinate
    a = torch.addcmul(torch.addcmul(h[2][:, None], h[0][:, None], key.us), h[1][:, None], key.vs)
    rho = key.state.mu
    a0, a1, a2 = a.unbind(0)
    w = a2 + rho * b2
    nu = b0 * a2 - a0 * b2
    nv = b1 * a2 - a1 * b2
    norm = torch.hypot(nu, nv)
    w2 = torch.clamp(w * w, min=1e-12)
    j = norm / w2
    along = (key.grad[0] * nu + key.grad[1] * nv).abs() / torch.clamp(norm, min=1e-9)
    front = w > 1e-9
    wc = torch.clamp(w, min=1e-9)
    cu, cv = image_centre(camera)
    visible = (
        front
        & (((a0 + rho * b0) / wc - cu).abs() <= cu - margin)
        & (((a1 + rho * b1) / wc - cv).abs() <= cv - margin)
    )
    return FrameGeometry(a, (b0, b1, b2), j, along, visible)


def frame_projection(
    camera: PinholeCamera, T_fk: np.ndarray, device: torch.device
) -> tuple[torch.Tensor, tuple[float, float, float]]:
    """The frame's pixel-to-pixel homography at infinity ``K R_fk K^-1`` as float32 rows of its
    columns (``h[k]``: column k), and ``K t_fk``'s float32 values as Python numbers (as operands
    they are cast back to float32: the same products, without a 0-d tensor select per use).
    :func:`frame_geometry` and its native twin (``native_choose``) read the same values."""
    K = np.asarray(camera.K, dtype=np.float64)
    H = K @ T_fk[:3, :3] @ np.linalg.inv(K)
    h = torch.as_tensor(H.T, dtype=torch.float32, device=device)
    b0, b1, b2 = (float(v) for v in (K @ T_fk[:3, 3]).astype(np.float32))
    return h, (b0, b1, b2)


def image_centre(camera: PinholeCamera) -> tuple[float, float]:
    """The image's centre in pixels (the visibility test measures from it)."""
    return 0.5 * (camera.width - 1), 0.5 * (camera.height - 1)


def row_motion(a: torch.Tensor, b: tuple[float, float, float], rho: torch.Tensor) -> torch.Tensor:
    """``|d p / d rho|`` (R,) of coordinate-first rows ``a`` (3, R) at inverse depths ``rho``
    (``EpipolarRays.parallax``), ``b`` as numbers: contiguous rows and no per-use selects of
    ``b`` (a third of the ops of the pixel-last form)."""
    return torch.hypot(*epipolar_motion(a.unbind(0), b, rho))


def grid_rows_in_place(
    a: torch.Tensor, b: tuple[float, float, float], width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``filter_search.normalised_rows`` of coordinate-first rows ``a`` (3, R), in place in ``a``
    (the caller's own gathered copy): the same numbers (``EpipolarRays._normalised``) without
    the pixel-first round trip (scale, concatenation, transposed copy)."""
    scale = torch.tensor([2.0 / (width - 1), 2.0 / (height - 1), 1.0], dtype=a.dtype, device=a.device)
    a[:2].mul_(scale[:2, None]).sub_(a[2])  # (a_k s_k) - a_2; a_2 s_2 = a_2 exactly
    b = torch.tensor(b, dtype=a.dtype, device=a.device) * scale
    return a, torch.cat((b[:2] - b[2:], b[2:]))
