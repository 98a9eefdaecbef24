"""The self-supervised loss terms (torch, differentiable in the network's log depth).

* :func:`sparse_log_l1` — L1 of log depth at the selected multi-view points: metric targets
  at ~4 % AbsRel (TUM), robust to the few wrong matches stage 1 lets through (L1 is the
  median's loss, so a minority of outliers cannot drag the depth);
* :func:`photometric` — SSIM + L1 between the keyframe and each neighbour warped through the
  predicted depth, per pixel the minimum over neighbours (occlusions; Monodepth2), with
  auto-masking of pixels that the unwarped neighbour explains at least as well (no parallax,
  untextured): dense, and metric because the poses are;
* :func:`smoothness` — edge-aware first-order smoothness of mean-normalised inverse depth.

Training evaluates them for a whole batch at once (``batch.py``: one kernel sequence for all
keyframes and neighbours, not one per keyframe), with every depth-independent part computed
once per keyframe (``prepared.py``): the keyframe's SSIM statistics (:func:`key_stats`), the
photometric error of the unwarped neighbours, the smoothness edge weights
(:func:`edge_weights`) and the points' sampling grids (:func:`point_grid`). The per-keyframe
functions below (:func:`photometric`, :func:`smoothness`, :func:`sparse_log_l1`) compute the
same quantities for one keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .warp import pixel_rays, warp_neighbours

#: The photometric error given to pixels a neighbour does not see (never the minimum).
INVALID = 1e3
C1, C2 = 0.01**2, 0.03**2


def point_grid(uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(N, 2) ``grid_sample`` coordinates of working-grid pixels ``uv`` (N, 2) of a ``width`` x
    ``height`` image (pixel centres; ``align_corners=False``)."""
    return torch.stack([(uv[:, 0] + 0.5) / width * 2 - 1, (uv[:, 1] + 0.5) / height * 2 - 1], dim=-1)


def sample_map(log_depth: torch.Tensor, uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Bilinear values of ``log_depth`` (1, 1, h, w) at working-grid pixels ``uv`` (N, 2) of a
    ``width`` x ``height`` image covering the same field of view (as the predictor's resize)."""
    grid = point_grid(uv, width, height)
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


def sparse_batch(
    log_depth: torch.Tensor, grid: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """Per-keyframe mean ``|log z_pred - log z_mv|`` for a batch -> (B,) (0 without points).

    ``log_depth`` (B, 1, h, w); ``grid`` (B, M, 2) point coordinates (:func:`point_grid`),
    ``target`` (B, M) log depths and ``mask`` (B, M) which of the M slots are points.
    """
    error = torch.where(mask, sparse_point_errors(log_depth, grid, target), 0.0)
    return error.sum(dim=1) / mask.sum(dim=1).clamp_min(1)


def sparse_point_errors(log_depth: torch.Tensor, grid: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, M) ``|log z_pred - log z_mv|`` at every point slot (padding slots included)."""
    values = F.grid_sample(
        log_depth, grid[:, None], mode='bilinear', padding_mode='border', align_corners=False
    ).reshape(grid.shape[0], -1)
    return (values - target).abs()


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


def _pad(t: torch.Tensor) -> torch.Tensor:
    return F.pad(t, (1, 1, 1, 1), mode='reflect')


@lru_cache(maxsize=16)
def _box_weight(channels: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return torch.full((channels, 1, 3, 3), 1.0 / 9.0, device=device, dtype=dtype)


def _box3(t: torch.Tensor) -> torch.Tensor:
    """3x3 window means of every channel (``avg_pool2d(t, 3, 1)``, as a depthwise convolution:
    the same sums, several times faster on the CPU forward and backward)."""
    return F.conv2d(t, _box_weight(t.shape[1], t.device, t.dtype), groups=t.shape[1])


@dataclass
class KeyStats:
    """The keyframe's side of :func:`ssim_error` (it is never warped, so computed once)."""

    image: torch.Tensor  # (K, C, H, W)
    mu: torch.Tensor  # local means over 3x3 windows
    mu_sq: torch.Tensor  # mu ** 2
    sigma: torch.Tensor  # local variances


def key_stats(image: torch.Tensor) -> KeyStats:
    """:class:`KeyStats` of ``image`` (K, C, H, W), computed as :func:`ssim_error` does."""
    mu = _box3(_pad(image))
    return KeyStats(image, mu, mu**2, _box3(_pad(image * image)) - mu**2)


def photo_error_to_key(x: torch.Tensor, key: KeyStats, alpha: float) -> torch.Tensor:
    """:func:`photo_error` ``(x, key.image, alpha)`` with the keyframe's statistics given:
    the three window means of ``x`` in one pooling pass -> (N, 1, H, W).

    ``key`` holds one keyframe (broadcast over ``x``) or one per row of ``x``.
    """
    y, c = key.image, x.shape[1]
    pooled = _box3(_pad(torch.cat([x, x * x, x * y.expand_as(x)], dim=1)))
    mu_x, xx, xy = pooled[:, :c], pooled[:, c : 2 * c], pooled[:, 2 * c :]
    sx = xx - mu_x**2
    sxy = xy - mu_x * key.mu
    num = (2 * mu_x * key.mu + C1) * (2 * sxy + C2)
    den = (mu_x**2 + key.mu_sq + C1) * (sx + key.sigma + C2)
    ssim = ((1 - num / den) / 2).clamp(0, 1).mean(dim=1, keepdim=True)
    l1 = (x - y).abs().mean(dim=1, keepdim=True)
    return alpha * ssim + (1 - alpha) * l1


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
    error over the pixels that are valid in some neighbour and not auto-masked (0 when none).
    """
    n, _, height, width = neighbours.shape
    stats = key_stats(key_image)
    batch = PhotometricBatch(
        neighbours=neighbours,
        stats=stats,
        identity=photo_error_to_key(neighbours, stats, alpha),
        rays=pixel_rays(torch.linalg.inv(k), height, width),
        k=k,
        t_ok=t_ok,
        owner=torch.zeros(n, dtype=torch.long, device=neighbours.device),
        slots=torch.arange(n, device=neighbours.device)[None],
    )
    return photometric_batch(log_depth, batch, alpha)[0]


@dataclass
class PhotometricBatch:
    """Every (keyframe, neighbour) pair of a batch: P pairs, keyframe b owns ``slots[b]``."""

    neighbours: torch.Tensor  # (P, C, h, w)
    stats: KeyStats  # the owning keyframe's, one row per pair (or one row for all)
    identity: torch.Tensor  # (P, 1, h, w) error of the unwarped neighbour
    rays: torch.Tensor  # (3, h*w) or (P, 3, h*w)
    k: torch.Tensor  # (3, 3) or (P, 3, 3)
    t_ok: torch.Tensor  # (P, 4, 4)
    owner: torch.Tensor  # (P,) batch index of each pair's keyframe
    #: (B, M) pair indices of each keyframe, padded with P (a row of INVALID errors).
    slots: torch.Tensor


def photometric_batch(log_depth: torch.Tensor, batch: PhotometricBatch, alpha: float) -> torch.Tensor:
    """:func:`photometric` for every keyframe of ``log_depth`` (B, 1, h, w) at once -> (B,)."""
    depth = torch.exp(log_depth)[batch.owner]
    warped, valid = warp_neighbours(batch.neighbours, depth, batch.k, batch.t_ok, batch.rays)
    reproj = torch.where(valid, photo_error_to_key(warped, batch.stats, alpha), INVALID)
    identity = torch.where(valid, batch.identity, INVALID)
    pad = reproj.new_full((1, *reproj.shape[1:]), INVALID)
    best, _ = torch.cat([reproj, pad])[batch.slots].min(dim=1)  # (B, 1, h, w)
    best_identity, _ = torch.cat([identity, pad])[batch.slots].min(dim=1)
    keep = (best < best_identity) & (best < INVALID)
    total = torch.where(keep, best, 0.0).sum(dim=(1, 2, 3))
    return total / keep.sum(dim=(1, 2, 3)).clamp_min(1)


def edge_weights(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``exp(-|dI/dx|)`` (B, 1, h, w-1) and ``exp(-|dI/dy|)`` (B, 1, h-1, w) of ``image``
    (channel mean): where the image has an edge, the depth may jump."""
    ix = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(dim=1, keepdim=True)
    iy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(dim=1, keepdim=True)
    return torch.exp(-ix), torch.exp(-iy)


def smoothness_batch(log_depth: torch.Tensor, weight_x: torch.Tensor, weight_y: torch.Tensor) -> torch.Tensor:
    """Per-keyframe edge-aware smoothness of mean-normalised inverse depth -> (B,)
    (``weight_x``, ``weight_y`` from :func:`edge_weights`)."""
    inv = torch.exp(-log_depth)
    inv = inv / inv.mean(dim=(2, 3), keepdim=True).clamp_min(1e-6)
    dx = (inv[..., :, 1:] - inv[..., :, :-1]).abs()
    dy = (inv[..., 1:, :] - inv[..., :-1, :]).abs()
    return (dx * weight_x).mean(dim=(1, 2, 3)) + (dy * weight_y).mean(dim=(1, 2, 3))


def smoothness(log_depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of mean-normalised inverse depth (``image`` on the same grid)."""
    return smoothness_batch(log_depth, *edge_weights(image)).mean()
