"""The separable window sums: OpenCV on CPU float32, shifted slices elsewhere, the same sums."""

from __future__ import annotations

import pytest
import torch

from depth_fusion_ros.fusion.gaussian import gaussian_kernel
from depth_fusion_ros.separable import separable_sum


@pytest.mark.parametrize('replicate', [False, True])
@pytest.mark.parametrize('shape', [(240, 320), (3, 60, 80), (2, 3, 9, 11), (1, 5, 7)])
def test_the_opencv_path_sums_as_the_slices_do(shape: tuple[int, ...], replicate: bool) -> None:
    """float32 on the CPU goes through OpenCV; float64 keeps the slices (the reference here),
    with zero or repeated borders, one plane or a batch, and kernels wider than the image."""
    x = torch.rand(shape, generator=torch.Generator().manual_seed(len(shape)))
    for taps in (gaussian_kernel(8.0, torch.device('cpu'))[0].tolist(), [0.25, 0.5, 0.25]):
        fast = separable_sum(x, taps, replicate)
        reference = separable_sum(x.double(), taps, replicate)
        assert fast.dtype == torch.float32 and fast.shape == x.shape
        assert torch.allclose(fast.double(), reference, rtol=1e-5, atol=1e-6)
