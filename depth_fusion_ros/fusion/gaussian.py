"""Gaussian window sums on torch (zero padding): the normalised convolutions of the fusion.

Stage 3 (``consistency.py``) and the confidence's agreement factor (``agreement.py``) both
average values over the multi-view points around each pixel: ``Σ g·x / Σ g·[point]`` with a
separable Gaussian ``g``. The sums run as two 1-D passes on any device.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional


def gaussian_kernel(sigma: float, device: torch.device) -> tuple[torch.Tensor, float]:
    """The 1-D taps (peak 1, cut at 3 sigma) and the centre tap."""
    radius = max(1, int(np.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32, device=device)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g, float(g[radius])


def gaussian_sum(images: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian sum (zero padding) of an ``(H, W)`` or ``(N, H, W)`` tensor.

    A sum of shifted slices, as ``multiview.cost_volume.gaussian_blur``: on one CPU thread
    2.2x faster than two ``conv2d`` passes for the 49 taps of sigma 8 (3.4 against 7.6 ms for
    three 320x240 images), and it runs unchanged on CUDA.
    """
    r = (g.numel() - 1) // 2
    h, w = images.shape[-2:]
    taps = g.tolist()
    padded = functional.pad(images, (r, r, 0, 0))
    rows = padded[..., :w] * taps[0]
    for k in range(1, len(taps)):
        rows.add_(padded[..., k : k + w], alpha=taps[k])
    padded = functional.pad(rows, (0, 0, r, r))
    out = padded[..., :h, :] * taps[0]
    for k in range(1, len(taps)):
        out.add_(padded[..., k : k + h, :], alpha=taps[k])
    return out
