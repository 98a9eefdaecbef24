"""Gaussian window sums on torch (zero padding): the normalised convolutions of the fusion.

Stage 3 (``consistency.py``) and the confidence's agreement factor (``agreement.py``) both
average values over the multi-view points around each pixel: ``Σ g·x / Σ g·[point]`` with a
separable Gaussian ``g``. The sums run as two 1-D passes on any device.
"""

from __future__ import annotations

import cv2
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
    taps ``g``: OpenCV's ``sepFilter2D`` for float32 on the CPU, ``separable.separable_sum``
    elsewhere (CUDA). Why two: the fusion's agreement factor sums three 320x240 maps with 49
    taps per keyframe, 7.3 ms as torch slices on one CPU thread and 3.3 ms with OpenCV's
    vectorised filter; the sums agree to float32 rounding (5e-7 relative)."""
    if images.device.type != 'cpu' or images.dtype != torch.float32 or images.dim() not in (2, 3):
        return separable_sum(images, g.tolist())
    taps = g.detach().cpu().numpy().astype(np.float32)
    planes = images.detach().numpy()
    if images.dim() == 2:
        return torch.from_numpy(_sep_filter(planes, taps))
    return torch.from_numpy(np.stack([_sep_filter(plane, taps) for plane in planes]))


def _sep_filter(plane: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """One plane's zero-padded separable sum (``anchor`` the centre tap, no delta, no scaling)."""
    return cv2.sepFilter2D(
        np.ascontiguousarray(plane), cv2.CV_32F, taps, taps, borderType=cv2.BORDER_CONSTANT
    )
