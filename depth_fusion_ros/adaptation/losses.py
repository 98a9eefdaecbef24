"""The self-supervised loss terms (torch, differentiable in the network's log depth).

* :func:`sparse_log_l1` — L1 of log depth at the selected multi-view points: metric targets
  at ~4 % AbsRel (TUM), robust to the few wrong matches stage 1 lets through (L1 is the
  median's loss, so a minority of outliers cannot drag the depth);
* :func:`photometric` — SSIM + L1 between the keyframe and each neighbour warped through the
  predicted depth, per pixel the minimum over neighbours (occlusions; Monodepth2), with
  auto-masking of pixels that the unwarped neighbour explains at least as well (no parallax,
  untextured): dense, and metric because the poses are;
* :func:`smoothness` — edge-aware first-order smoothness of mean-normalised inverse depth.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .warp import warp_neighbours


def sample_map(log_depth: torch.Tensor, uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Bilinear values of ``log_depth`` (1, 1, h, w) at working-grid pixels ``uv`` (N, 2) of a
    ``width`` x ``height`` image covering the same field of view (as the predictor's resize)."""
    grid = torch.stack([(uv[:, 0] + 0.5) / width * 2 - 1, (uv[:, 1] + 0.5) / height * 2 - 1], dim=-1)
    out = F.grid_sample(
        log_depth, grid[None, None], mode='bilinear', padding_mode='border', align_corners=False
    )
    return out.reshape(-1)


def sparse_log_l1(
    log_depth: torch.Tensor, uv: torch.Tensor, target_log: torch.Tensor, width: int, height: int
) -> torch.Tensor:
    """Mean ``|log z_pred - log z_mv|`` at the points (0 when there are none)."""
    if uv.shape[0] == 0:
        return log_depth.sum() * 0.0
    return (sample_map(log_depth, uv, width, height) - target_log).abs().mean()


def ssim_error(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel ``(1 - SSIM) / 2`` over 3x3 windows, averaged over channels -> (N, 1, H, W)."""
    c1, c2 = 0.01**2, 0.03**2
    pad = lambda t: F.pad(t, (1, 1, 1, 1), mode='reflect')  # noqa: E731
    mu_x, mu_y = F.avg_pool2d(pad(x), 3, 1), F.avg_pool2d(pad(y), 3, 1)
    sx = F.avg_pool2d(pad(x * x), 3, 1) - mu_x**2
    sy = F.avg_pool2d(pad(y * y), 3, 1) - mu_y**2
    sxy = F.avg_pool2d(pad(x * y), 3, 1) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sx + sy + c2)
    return ((1 - num / den) / 2).clamp(0, 1).mean(dim=1, keepdim=True)


def photo_error(x: torch.Tensor, y: torch.Tensor, alpha: float) -> torch.Tensor:
    """``alpha`` SSIM error + ``(1 - alpha)`` L1 per pixel -> (N, 1, H, W)."""
    l1 = (x - y).abs().mean(dim=1, keepdim=True)
    return alpha * ssim_error(x, y) + (1 - alpha) * l1


def photometric(
    log_depth: torch.Tensor,
    key_image: torch.Tensor,
    neighbours: torch.Tensor,
    k: torch.Tensor,
    t_ok: torch.Tensor,
    alpha: float = 0.85,
) -> torch.Tensor:
    """Min-over-neighbours photometric error with auto-masking.

    ``log_depth`` (1, 1, h, w); ``key_image`` (1, C, h, w) and ``neighbours`` (N, C, h, w) in
    [0, 1] on the same grid; ``k`` (3, 3) for that grid; ``t_ok`` (N, 4, 4). Returns the mean
    error over the pixels that are valid in some neighbour and not auto-masked.
    """
    warped, valid = warp_neighbours(neighbours, torch.exp(log_depth), k, t_ok)
    key = key_image.expand_as(warped)
    big = torch.full_like(valid, 1e3, dtype=warped.dtype)
    reproj = torch.where(valid, photo_error(warped, key, alpha), big)
    identity = torch.where(valid, photo_error(neighbours, key, alpha), big)
    best, _ = reproj.min(dim=0)
    best_identity, _ = identity.min(dim=0)
    keep = (best < best_identity) & (best < 1e3)
    if not bool(keep.any()):
        return log_depth.sum() * 0.0
    return best[keep].mean()


def smoothness(log_depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of mean-normalised inverse depth (``image`` on the same grid)."""
    inv = torch.exp(-log_depth)
    inv = inv / inv.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    dx = (inv[..., :, 1:] - inv[..., :, :-1]).abs()
    dy = (inv[..., 1:, :] - inv[..., :-1, :]).abs()
    ix = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(dim=1, keepdim=True)
    iy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(dim=1, keepdim=True)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()
