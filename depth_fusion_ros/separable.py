"""Separable weighted window sums on torch: the one implementation of the blurs and Gaussian
window sums of the multi-view and fusion stages.

On the CPU, float32 images go through OpenCV's vectorised ``sepFilter2D``, one plane at a
time: 3.3 against 7.3 ms for the fusion's 49 taps over three 320x240 images, 0.07 against
0.32 ms for the multi-view blur's 3 taps over one (one thread), equal to float32 rounding.
Elsewhere (CUDA, other dtypes) a sum of shifted slices, first along the rows, then along the
columns: for the few- to few-dozen-tap kernels used here several times faster than two
``conv2d`` passes, and the same code on every device.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import torch
from torch.nn import functional


def separable_sum(images: torch.Tensor, taps: Sequence[float], replicate: bool = False) -> torch.Tensor:
    """``Σ_k taps[k] · x[i + k - r]`` along the width, then the height, of ``(..., H, W)``
    ``images`` (``len(taps) = 2r + 1``): zero padding, or the border pixels repeated with
    ``replicate``."""
    if images.device.type == 'cpu' and images.dtype == torch.float32 and images.dim() >= 2:
        return _opencv_sum(images, taps, replicate)
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


def _opencv_sum(images: torch.Tensor, taps: Sequence[float], replicate: bool) -> torch.Tensor:
    """:func:`separable_sum` of a CPU float32 ``(..., H, W)`` tensor with ``sepFilter2D`` (the
    kernel's centre as anchor, no scaling), plane by plane."""
    kernel = np.asarray(taps, dtype=np.float32)
    border = cv2.BORDER_REPLICATE if replicate else cv2.BORDER_CONSTANT
    planes = images.detach().reshape(-1, *images.shape[-2:]).numpy()
    out = np.empty(planes.shape, dtype=np.float32)
    for i, plane in enumerate(planes):
        out[i] = cv2.sepFilter2D(np.ascontiguousarray(plane), cv2.CV_32F, kernel, kernel, borderType=border)
    return torch.from_numpy(out.reshape(images.shape))
