"""Window reductions over the keyframe's pixel grid (hole filling, the seed bracket's ranges).

Separable shifted slices: several times faster on CPU than ``avg_pool2d`` or a max pool for
the filter's small windows, and exact (the same values to the bit as combining the slices
one after the other).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)


def box_sum(maps: torch.Tensor, r: int) -> torch.Tensor:
    """Sum of each ``(C, H, W)`` map over the ``(2r + 1)^2`` window (zeros outside): separable
    shifted slices, several times faster on CPU than ``avg_pool2d`` for these small windows."""
    return window_reduce(F.pad(maps, (r, r, r, r)), r, lambda acc, x: acc.add_(x))


def window_reduce(
    padded: torch.Tensor, r: int, combine: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
) -> torch.Tensor:
    """``combine`` (in place into its first argument) over each ``(2r + 1)^2`` window of the
    ``(..., H + 2r, W + 2r)`` padded maps, separably: along the rows, then the columns, in the
    order (and so to the bits) of combining the shifted slices one after the other."""
    h, w = padded.shape[-2] - 2 * r, padded.shape[-1] - 2 * r
    across = padded[..., :, 0:w].clone()
    for k in range(1, 2 * r + 1):
        combine(across, padded[..., :, k : k + w])
    out = across[..., 0:h, :].clone()
    for k in range(1, 2 * r + 1):
        combine(out, across[..., k : k + h, :])
    return out
