"""Separable weighted window sums on torch: the one implementation of the blurs and Gaussian
window sums of the multi-view and fusion stages.

A sum of shifted slices, first along the rows, then along the columns. For the few- to
few-dozen-tap kernels used here it is several times faster on CPU than two ``conv2d`` passes
(3.4 against 7.6 ms for 49 taps over three 320x240 images, one thread) and runs unchanged on
CUDA.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.nn import functional


def separable_sum(images: torch.Tensor, taps: Sequence[float], replicate: bool = False) -> torch.Tensor:
    """``Σ_k taps[k] · x[i + k - r]`` along the width, then the height, of ``(..., H, W)``
    ``images`` (``len(taps) = 2r + 1``): zero padding, or the border pixels repeated with
    ``replicate``."""
    r = (len(taps) - 1) // 2
    h, w = images.shape[-2:]
    rows = _weighted_slices(_pad(images, (r, r, 0, 0), replicate), taps, w, dim=-1)
    return _weighted_slices(_pad(rows, (0, 0, r, r), replicate), taps, h, dim=-2)


def _weighted_slices(padded: torch.Tensor, taps: Sequence[float], size: int, dim: int) -> torch.Tensor:
    out = padded.narrow(dim, 0, size) * taps[0]
    for k in range(1, len(taps)):
        out.add_(padded.narrow(dim, k, size), alpha=taps[k])
    return out


def _pad(images: torch.Tensor, widths: tuple[int, int, int, int], replicate: bool) -> torch.Tensor:
    if not replicate:
        return functional.pad(images, widths)
    # replicate padding takes a channel dimension: (..., H, W) -> (N, 1, H, W) and back
    flat = images.reshape(-1, 1, *images.shape[-2:])
    padded = functional.pad(flat, widths, mode='replicate')
    return padded.reshape(*images.shape[:-2], *padded.shape[-2:])
