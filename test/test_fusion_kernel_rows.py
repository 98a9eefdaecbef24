"""The fusion kernels never see a single pixel: a one-pixel fix-up is padded to two rows.

Why: the compiled kernels are dynamic in the pixel count from 2 up, and torch.compile
specialises (recompiles) for a size of 1. A live keyframe whose fast mode fixed up exactly
one pixel recompiled the kernel mid-stream (`TORCH_LOGS=recompiles`: `2 <= args[0].x.size()[0]`
failed) while the keyframes behind it were dropped (docs/performance.md "GPU").
"""

from __future__ import annotations

import functools

import torch

from depth_fusion_ros.fusion.chunk_sums import chunk_sums_inplace
from depth_fusion_ros.fusion.interpolation import MIN_KERNEL_ROWS, _offsets_at
from depth_fusion_ros.fusion.weights import WeightParams, samples_at

PARAMS = WeightParams()
WIDTH, HEIGHT = 16, 12


def _maps() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(4)
    s = 1.0 + torch.rand(WIDTH * HEIGHT, generator=g)
    return s, 0.01 * torch.randn(WIDTH * HEIGHT, generator=g), 0.01 * torch.randn(WIDTH * HEIGHT, generator=g)


def test_one_pixel_is_computed_in_a_padded_call_with_the_batch_numbers() -> None:
    s, gx, gy = _maps()
    points = samples_at(torch.tensor([3, 40, 77, 150, 181]), WIDTH, s, gx, gy)
    v = torch.tensor([0.1, -0.2, 0.05, 0.3, -0.1])
    rows_seen: list[int] = []
    eager = functools.partial(chunk_sums_inplace, params=PARAMS)

    def kernel(p, q, v, lw):
        rows_seen.append(int(p.x.shape[0]))
        return eager(p, q, v, lw)

    batch = samples_at(torch.tensor([5, 60, 99, 120]), WIDTH, s, gx, gy)
    want, want_support, _ = _offsets_at(batch, points, v, None, kernel, 1 << 20, PARAMS)
    for i, pixel in enumerate((5, 60, 99, 120)):
        rows_seen.clear()
        got, support, _ = _offsets_at(
            samples_at(torch.tensor([pixel]), WIDTH, s, gx, gy), points, v, None, kernel, 1 << 20, PARAMS
        )
        assert rows_seen == [MIN_KERNEL_ROWS] and got.shape == (1,)
        torch.testing.assert_close(got[0], want[i])
        torch.testing.assert_close(support[0], want_support[i])
