"""Carry per-pixel inverse-depth estimates from one camera into another (LSD-SLAM propagation).

Each estimate is back-projected at its mean inverse depth, moved by the relative pose and
projected into the other camera at the nearest pixel. Where several land on one pixel the
nearest wins (a z-buffer: the others are occluded). The variance is transported to first
order (``rho' = rho z / z'``, so ``sigma' = sigma (rho' / rho)^2``) and, for a new keyframe,
inflated (``propagation_inflation``, plus a relative std ``propagation_relative_sigma``):
the new camera sees the surface under another angle, and nearest-pixel rounding moves the
point, so the carried estimate is a prior to re-check, not a measurement. The Beta
parameters (the evidence for the pixel being an inlier) are carried unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..true_indices import true_indices


@dataclass
class Warped:
    """Target pixel (flat index) of each source estimate that lands, the source rows, and rho'."""

    target: torch.Tensor  # (L,) long: v * W + u in the target image
    source: torch.Tensor  # (L,) long: rows of the source arrays
    rho: torch.Tensor  # (L,) inverse depth in the target camera
    scale: torch.Tensor  # (L,) rho' / rho (the variance is scaled by its 4th power)


def warp_estimates(
    us: torch.Tensor,
    vs: torch.Tensor,
    rho: torch.Tensor,
    K: np.ndarray,
    T_tk: np.ndarray,
    size: tuple[int, int],
    rho_range: tuple[float, float],
) -> Warped:
    """Nearest-pixel, z-buffered warp of estimates at pixels ``(us, vs)`` with inverse depth ``rho``.

    ``T_tk`` maps source-camera points to the target camera; ``size`` = (W, H). Estimates that
    leave the image, go behind the camera or out of ``rho_range`` are not carried.
    """
    dev, dtype = rho.device, rho.dtype
    w, h = int(size[0]), int(size[1])
    Kt = torch.as_tensor(K, dtype=dtype, device=dev)
    R = torch.as_tensor(T_tk[:3, :3], dtype=dtype, device=dev)
    t = torch.as_tensor(T_tk[:3, 3], dtype=dtype, device=dev)
    x = (us.to(dtype) - Kt[0, 2]) / Kt[0, 0]
    y = (vs.to(dtype) - Kt[1, 2]) / Kt[1, 1]
    ray = torch.stack((x, y, torch.ones_like(x)), dim=1)  # (M, 3), the point is ray / rho
    p = ray @ R.T + t[None, :] * rho[:, None]  # = rho * (R X + t): same direction, z' * rho
    zr = p[:, 2]
    front = zr > 1e-9
    zs = torch.where(front, zr, torch.ones_like(zr))
    u = torch.round(Kt[0, 0] * p[:, 0] / zs + Kt[0, 2])
    v = torch.round(Kt[1, 1] * p[:, 1] / zs + Kt[1, 2])
    rho_t = rho / zs  # 1 / z' = rho / (rho z')
    keep = front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    keep &= (rho_t >= rho_range[0]) & (rho_t <= rho_range[1])
    # Gathers by index_select: the same values as advanced / boolean-mask indexing, several
    # times cheaper on CPU.
    source = true_indices(keep)
    target = (v.index_select(0, source) * w + u.index_select(0, source)).long()
    rho_t = rho_t.index_select(0, source)
    nearest = torch.full((h * w,), -1.0, dtype=dtype, device=dev)
    nearest.scatter_reduce_(0, target, rho_t, reduce='amax')
    win = true_indices(rho_t >= nearest.index_select(0, target))
    source, target, rho_t = (t.index_select(0, win) for t in (source, target, rho_t))
    return Warped(target, source, rho_t, rho_t / rho.index_select(0, source))
