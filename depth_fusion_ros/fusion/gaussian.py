"""Gaussian window sums on torch (zero padding): the normalised convolutions of the fusion.

Stage 3 (``consistency.py``) and the confidence's agreement factor (``agreement.py``) both
average values over the multi-view points around each pixel: ``Σ g·x / Σ g·[point]`` with a
separable Gaussian ``g``. The sums run as two 1-D passes on any device.
"""

from __future__ import annotations

import numpy as np
import torch

from ..separable import separable_sum


def gaussian_kernel(sigma: float, device: torch.device) -> tuple[torch.Tensor, float]:
    """The 1-D taps (peak 1, cut at 3 sigma) and the centre tap."""
    radius = max(1, int(np.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32, device=device)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g, float(g[radius])


def gaussian_sum(images: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian sum (zero padding) of an ``(H, W)`` or ``(N, H, W)`` tensor with the
    taps ``g`` (``separable.separable_sum``)."""
    return separable_sum(images, g.tolist())
