"""The native descriptor table (``multiview/describe_table.c``) against OpenCV's descriptors.

For every patch layout, stride, blur, channel count and visibility band the filter may be
configured with, and image sizes that are not a multiple of the kernel's eight pixels, the
kernel must give OpenCV's numbers to float32 rounding, in a table the searches read in place;
split over threads it must give the same numbers; and it must decline what it was not written
for, leaving OpenCV or torch to describe.
"""

from __future__ import annotations

import pytest
import torch
from native_calls import count_native_calls

from depth_fusion_ros import native_build
from depth_fusion_ros.multiview import descriptors, native_cost, native_descriptors
from depth_fusion_ros.multiview.descriptors import PATCH_OFFSETS, patch_descriptors

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _native_or_skip() -> None:
    if native_descriptors._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _image(height: int, width: int, seed: int = 0) -> torch.Tensor:
    """Texture at several scales, and a flat patch (near-zero descriptors, the eps floor)."""
    g = torch.Generator().manual_seed(seed)
    fine = torch.rand(1, 1, height, width, generator=g)
    coarse = torch.nn.functional.interpolate(
        torch.rand(1, 1, height // 4 + 1, width // 4 + 1, generator=g), size=(height, width), mode='bilinear'
    )
    image = (0.3 * fine + 0.7 * coarse)[0]
    image[:, : height // 3, : width // 3] = 0.5
    return image


def _both(monkeypatch, image: torch.Tensor, **kwargs) -> tuple[torch.Tensor, torch.Tensor]:
    mine = patch_descriptors(image, channels_last=True, **kwargs)
    with monkeypatch.context() as off:
        off.setattr(native_descriptors, '_library', lambda: None)
        theirs = patch_descriptors(image, channels_last=True, **kwargs)
    return mine, theirs


@pytest.mark.parametrize(
    ('patch', 'stride', 'sigma', 'channels', 'margin', 'size'),
    [
        ('box', 2, 0.5, 6, 4, (240, 320)),  # the defaults
        ('box', 2, 0.5, 6, 4, (29, 37)),  # a last group of fewer than eight pixels
        ('box', 1, 0.0, 0, None, (31, 45)),  # no blur, all eight channels, no band
        ('box', 3, 1.0, 7, 6, (40, 53)),  # a five-tap blur, seven channels and the band: a full block
        ('cross', 2, 0.5, 4, 4, (33, 47)),
        ('cross', 1, 0.5, 2, 0, (9, 11)),  # a band of zero width, an image smaller than the patch's reach
        ('box', 2, 0.5, 6, 4, (1, 1)),
    ],
)
def test_the_native_table_is_opencvs_descriptors(monkeypatch, patch, stride, sigma, channels, margin, size):
    _native_or_skip()
    image = _image(*size)
    kwargs = dict(patch=patch, stride=stride, blur_sigma=sigma, visibility_margin=margin, channels=channels)
    mine, theirs = _both(monkeypatch, image, **kwargs)
    assert mine.shape == theirs.shape
    assert torch.allclose(mine, theirs, rtol=0.0, atol=1e-5)
    if margin is not None:  # the band: exactly zero descriptors, the visibility channel exact
        assert torch.equal(mine[:, -1], theirs[:, -1])
        band = mine[:, -1:].expand_as(mine[:, :-1]) == 0
        assert not bool(mine[:, :-1][band].any())
    # the searches read either in place: no copy into their table
    assert native_cost._table_in_place(mine) is not None
    assert native_cost._table_in_place(theirs) is not None
    assert mine.stride() == theirs.stride()


def test_the_descriptors_are_unit_zncc_vectors(monkeypatch):
    """What the matcher relies on: a textured pixel's descriptor has (nearly) unit norm, a flat
    one is shortened by eps towards zero."""
    _native_or_skip()
    image = _image(60, 80)
    desc = patch_descriptors(image, visibility_margin=4, channels=6, channels_last=True)[0, :6]
    norm = desc.pow(2).sum(0).sqrt()
    assert float(norm[40:56, 40:76].min()) > 0.9
    assert float(norm[6:15, 6:20].max()) < 1e-3  # the flat corner


def test_rows_split_over_threads_give_the_same_numbers(monkeypatch):
    _native_or_skip()
    image = _image(97, 131, seed=3)
    one = patch_descriptors(image, visibility_margin=4, channels=6, channels_last=True)
    monkeypatch.setattr(native_descriptors, 'THREAD_MIN_PIXELS', 1)
    torch.set_num_threads(2)
    two = patch_descriptors(image, visibility_margin=4, channels=6, channels_last=True)
    assert torch.equal(one, two)


def test_the_kernel_declines_what_it_was_not_written_for(monkeypatch):
    _native_or_skip()
    calls = count_native_calls(monkeypatch, descriptors, 'native_table')
    two = torch.stack([_image(20, 30)[0], _image(20, 30, seed=1)[0]])
    patch_descriptors(two, visibility_margin=4, channels=6, channels_last=True)  # two images
    patch_descriptors(_image(20, 30).double(), visibility_margin=4, channels=6, channels_last=True)
    patch_descriptors(_image(20, 30).requires_grad_(), visibility_margin=4, channels=6, channels_last=True)
    patch_descriptors(_image(20, 30), visibility_margin=4, channels=0, channels_last=True)  # 8 + 1 channels
    assert calls == [False, False, False, False]
    patch_descriptors(_image(20, 30), visibility_margin=4, channels=6)  # planar: not asked
    assert calls == [False, False, False, False]
    patch_descriptors(_image(20, 30), visibility_margin=4, channels=6, channels_last=True)
    assert calls[-1] is True


def test_every_layout_fits_the_kernels_taps():
    assert max(len(offsets) for offsets in PATCH_OFFSETS.values()) <= native_descriptors.TAPS
