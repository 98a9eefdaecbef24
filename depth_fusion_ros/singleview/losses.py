"""Training losses on log depth: Eigen et al.'s scale-invariant loss plus a gradient term.

With ``d = log(prediction) - log(ground truth)`` over the valid pixels of one image,

* scale-invariant (Eigen, Puhrsch & Fergus, NIPS 2014, eq. 4):
  ``L_si = (1/n) Σ d² − (λ/n²) (Σ d)²``; λ = 1 ignores the global scale entirely, λ = 0
  is plain log-MSE; Eigen trained with λ = 0.5, which still learns metric scale but does
  not let a global scale error dominate the local structure;
* gradient matching (Eigen & Fergus, ICCV 2015, eq. 2):
  ``L_grad = (1/n) Σ [(∇x d)² + (∇y d)²]`` over pixels whose neighbour is valid too,
  which asks for the right local structure (edges, planes) the fusion relies on.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)


def log_depth_target(depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log depth with invalid pixels set to 0, valid mask)`` for a NaN-holed depth tensor."""
    valid = torch.isfinite(depth) & (depth > 0)
    log_gt = torch.where(valid, depth, torch.ones_like(depth)).log()
    return log_gt, valid


def upsample_to(pred: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of (B, 1, h, w) predictions to ``size`` (the paper's upsampling)."""
    if tuple(pred.shape[-2:]) == tuple(size):
        return pred
    return F.interpolate(pred, size=size, mode='bilinear', align_corners=False)


def scale_invariant_loss(
    log_pred: torch.Tensor, log_gt: torch.Tensor, valid: torch.Tensor, lam: float = 0.5
) -> torch.Tensor:
    """Mean over images of ``(1/n) Σ d² − (λ/n²)(Σ d)²``; images without valid pixels are skipped."""
    m = valid.to(log_pred.dtype).flatten(1)
    d = (log_pred - log_gt).flatten(1) * m
    n = m.sum(dim=1)
    has = n > 0
    n = n.clamp(min=1)
    per_image = (d * d).sum(dim=1) / n - lam * d.sum(dim=1) ** 2 / (n * n)
    return per_image[has].mean() if bool(has.any()) else log_pred.sum() * 0


def gradient_loss(log_pred: torch.Tensor, log_gt: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean squared horizontal and vertical differences of the log error where both pixels are valid."""
    d = log_pred - log_gt
    m = valid.to(d.dtype)
    gx = (d[..., :, 1:] - d[..., :, :-1]) * m[..., :, 1:] * m[..., :, :-1]
    gy = (d[..., 1:, :] - d[..., :-1, :]) * m[..., 1:, :] * m[..., :-1, :]
    n = (m[..., :, 1:] * m[..., :, :-1]).sum() + (m[..., 1:, :] * m[..., :-1, :]).sum()
    return ((gx * gx).sum() + (gy * gy).sum()) / n.clamp(min=1)


def resize_target(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Nearest-neighbour resize of (B, 1, H, W) ground truth, so holes and edges never blend."""
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth
    return F.interpolate(depth, size=size, mode='nearest')


def depth_loss(
    log_pred: torch.Tensor, depth: torch.Tensor, si_lambda: float = 0.5, grad_weight: float = 1.0
) -> torch.Tensor:
    """Training loss of a (B, 1, h, w) log-depth prediction against (B, 1, H, W) metric depth
    (NaN = unknown), at the prediction's resolution (as Eigen et al. train): the ground truth
    is resampled to it, which is also cheaper than upsampling the prediction."""
    depth = resize_target(depth, tuple(log_pred.shape[-2:]))
    log_gt, valid = log_depth_target(depth)
    loss = scale_invariant_loss(log_pred, log_gt, valid, si_lambda)
    if grad_weight > 0:
        loss = loss + grad_weight * gradient_loss(log_pred, log_gt, valid)
    return loss
