"""Inverse warping: a posed neighbour image resampled into the keyframe through a depth map.

For each keyframe pixel ``p`` with depth ``z(p)``: back-project ``X = z K^-1 p``, move it into
the neighbour with ``T_ok = inv(T_wo) T_wk``, project with ``K`` and sample the neighbour
bilinearly there. Where the depth is right (and the surface is Lambertian and visible), the
warped neighbour equals the keyframe; because ``T_ok`` is metric, so is the depth this favours.
Everything is torch, differentiable in the depth, and batched over neighbours.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)


def pixel_rays(k_inv: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(3, H*W) rays ``K^-1 [u, v, 1]`` for every pixel centre, row-major."""
    dev, dt = k_inv.device, k_inv.dtype
    v, u = torch.meshgrid(
        torch.arange(height, device=dev, dtype=dt), torch.arange(width, device=dev, dtype=dt), indexing='ij'
    )
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(height * width, device=dev, dtype=dt)])
    return k_inv @ pix


def warp_neighbours(
    images: torch.Tensor,
    depth: torch.Tensor,
    k: torch.Tensor,
    t_ok: torch.Tensor,
    rays: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp ``images`` (N, C, H, W) into the keyframe whose depth is ``depth`` (1, 1, H, W).

    ``k`` is the (3, 3) intrinsic matrix of this grid, ``t_ok`` (N, 4, 4) the keyframe-to-
    neighbour transforms. Returns the warped images and a validity mask (the point is in front
    of the neighbour and projects inside it) on the keyframe's grid: (N, C, H, W), (N, 1, H, W).

    The keyframe's grid may be a window of the neighbours' (``depth`` (., 1, h, w) smaller than
    ``images``, ``rays`` of the window's pixels in the whole grid's coordinates): the warp
    samples the whole neighbour images, and the outputs are (N, C, h, w), (N, 1, h, w).
    Batched over keyframes too: ``depth`` may be (N, 1, H, W) (each image's own keyframe
    depth), ``k`` (N, 3, 3) and ``rays`` (N, 3, H*W). ``rays`` (:func:`pixel_rays` of
    ``K^-1``) are computed when not given; training passes them, computed once per keyframe.
    """
    n, _, height, width = images.shape
    out_h, out_w = depth.shape[-2:]  # the keyframe's grid (a window of it: ``rays`` given)
    if rays is None:
        rays = pixel_rays(torch.linalg.inv(k), height, width)  # (3, HW)
    points = rays * depth.reshape(depth.shape[0], 1, -1)  # (1 or N, 3, HW)
    cam = t_ok[:, :3, :3] @ points + t_ok[:, :3, 3:]  # (N, 3, HW)
    z = cam[:, 2:3]
    proj = k @ cam
    front = z > 1e-3
    safe_z = torch.where(front, proj[:, 2:3], torch.ones_like(z))
    u = proj[:, 0] / safe_z[:, 0]
    v = proj[:, 1] / safe_z[:, 0]
    grid = torch.stack([(u + 0.5) / width * 2 - 1, (v + 0.5) / height * 2 - 1], dim=-1)
    grid = grid.reshape(n, out_h, out_w, 2)
    warped = F.grid_sample(images, grid, mode='bilinear', padding_mode='border', align_corners=False)
    inside = (grid.abs() < 1).all(dim=-1, keepdim=True).permute(0, 3, 1, 2)
    valid = inside & front.reshape(n, 1, out_h, out_w)
    return warped, valid
