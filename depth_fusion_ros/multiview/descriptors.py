"""Per-pixel patch descriptors: the photometric signature that every multi-view matcher compares.

The matching cost of the sweep, the TV baseline and the depth filter (``cost_volume.py``) is
the zero-mean normalised cross-correlation (ZNCC) of a small patch, as ``1 - ZNCC``. Why ZNCC
rather than the paper's raw intensity difference: TUM's auto-exposure changes gain and bias
between frames, 7-Scenes colour is JPEG and TUM has motion blur; ZNCC is exactly invariant to
a local gain and bias, bounded in ``[0, 2]`` (so one occluded neighbour cannot dominate the
average) and a patch averages out pixel noise. The patch is sampled as a per-pixel
*descriptor*: each image is blurred, the patch values around every pixel are stacked as
channels and normalised to zero mean and unit norm once per image. A bilinear lookup of the
descriptor image at a projected point then gives the (normalised) patch there, and the ZNCC is
a dot product. This assumes the patch keeps its shape between views (fronto-parallel, small
rotation), which the neighbour selection bounds. The normalisation adds ``eps`` to the norm so
texture-less patches get near-zero descriptors and a flat cost of about 1: they produce no
distinct minimum and so low photometric scores.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .. import vml_warmup  # noqa: F401  (MKL VML dispatch resolved before the first parallel sqrt)
from ..separable import separable_sum
from .native_cost import LANES
from .native_descriptors import KernelPatch, kernel_patch, native_table

#: Patch layouts (offsets in units of the patch stride): cost per lookup grows with the size.
PATCH_OFFSETS: dict[str, tuple[tuple[int, int], ...]] = {
    'cross': ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)),
    'box': tuple((dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)),
}


def patch_reach(patch: str, stride: int) -> int:
    """Largest pixel offset of a patch (the image margin its lookups need)."""
    return max(max(abs(dx), abs(dy)) for dx, dy in PATCH_OFFSETS[patch]) * stride


def check_patch(patch: str, stride: int) -> None:
    if patch not in PATCH_OFFSETS:
        raise ValueError(f'patch must be one of {sorted(PATCH_OFFSETS)}, got {patch!r}')
    if int(stride) < 1:
        raise ValueError(f'patch_stride must be >= 1, got {stride}')


def gaussian_blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(B, H, W)`` images (replicate borders); identity for sigma <= 0.

    Normalised taps over +-2.5 sigma (rounded: 3 taps for the default 0.5), summed as shifted
    slices (``separable.separable_sum``).
    """
    if sigma <= 0:
        return images
    return separable_sum(images, gaussian_taps(sigma), replicate=True)


@functools.lru_cache(maxsize=8)
def gaussian_taps(sigma: float) -> tuple[float, ...]:
    """:func:`gaussian_blur`'s normalised taps over +-2.5 sigma (rounded; at least one each
    side), for sigma > 0; made once per sigma (the filter blurs every frame)."""
    radius = max(1, round(2.5 * sigma))
    taps = [math.exp(-0.5 * (k / sigma) ** 2) for k in range(-radius, radius + 1)]
    total = sum(taps)
    return tuple(t / total for t in taps)


def zero_mean_basis(patch: str, channels: int = 0) -> np.ndarray:
    """Orthonormal rows spanning the zero-mean patches, lowest spatial frequencies first.

    ``(K, P)`` for a ``P``-tap patch, ``K = P - 1`` (all of them) or ``channels`` when given.
    Projecting a patch on all of them removes its mean and keeps every dot product between
    zero-mean patches, so the ZNCC is exact with one channel less to look up; keeping only the
    lowest frequencies is a ZNCC of a smoothed patch, cheaper still (each channel is one more
    bilinear lookup per pixel, sample and neighbour). ``box``: the 2-D DCT-II basis of the 3x3
    patch without its constant term, by increasing frequency; ``cross``: the two gradients,
    then a Laplacian and an anisotropy term.
    """
    taps = len(PATCH_OFFSETS[patch])
    if not (0 <= channels <= taps - 1):
        raise ValueError(
            f'descriptor_channels must be in [0, {taps - 1}] for the {patch!r} patch, got {channels}'
        )
    if patch == 'box':
        k = np.arange(3)
        dct = np.cos(np.pi * (2 * k[None, :] + 1) * k[:, None] / 6.0) * np.sqrt(2.0 / 3.0)
        dct[0] /= np.sqrt(2.0)
        order = sorted(((fy, fx) for fy in range(3) for fx in range(3)), key=lambda f: (f[0] + f[1], f))
        # PATCH_OFFSETS['box'] is row-major over (dy, dx) in -1..1, as np.outer's layout.
        rows = np.stack([np.outer(dct[fy], dct[fx]).reshape(-1) for fy, fx in order[1:]])
    else:  # cross: (0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)
        rows = np.array(
            [
                [0.0, -1.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 0.0, -1.0, 1.0],
                [4.0, -1.0, -1.0, -1.0, -1.0],
                [0.0, 1.0, 1.0, -1.0, -1.0],
            ]
        )
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    return rows[: channels or taps - 1]


def stage_descriptors(images: torch.Tensor, config: Any, channels_last: bool = False) -> torch.Tensor:
    """:func:`patch_descriptors` with a stage's matching settings (``MultiViewConfig`` or
    ``TVConfig``: ``patch``, ``patch_stride``, ``blur_sigma``, ``noise_floor``,
    ``descriptor_channels``), visibility band included, so both stages match the same way."""
    return patch_descriptors(
        images,
        config.patch,
        config.patch_stride,
        config.blur_sigma,
        config.noise_floor,
        patch_reach(config.patch, config.patch_stride),
        config.descriptor_channels,
        channels_last,
    )


@functools.lru_cache(maxsize=16)
def _basis(patch: str, channels: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """:func:`zero_mean_basis` as a tensor, built once per layout, dtype and device: the filter
    describes every frame, and building it (numpy, a sort, a copy) was a tenth of that."""
    return torch.as_tensor(zero_mean_basis(patch, channels), dtype=dtype, device=device)


def patch_descriptors(
    images: torch.Tensor,
    patch: str = 'box',
    stride: int = 2,
    blur_sigma: float = 0.5,
    eps: float = 0.01,
    visibility_margin: int | None = None,
    channels: int = 0,
    channels_last: bool = False,
) -> torch.Tensor:
    """Normalised zero-mean patch descriptors ``(B, K, H, W)`` of grey ``(B, H, W)`` images.

    Each pixel's ``P`` patch values are projected on :func:`zero_mean_basis` (``K = channels``
    rows, or all ``P - 1`` when 0) and divided by
    ``sqrt(|v|^2 + P eps^2)``: the dot product of two descriptors is the patch ZNCC, except
    that ``eps`` (grey levels in [0, 1], the noise floor) shortens low-contrast descriptors so
    their ZNCC with anything is near 0. With ``visibility_margin`` the descriptors are zeroed
    in a border band of that width and a last channel, 1 inside the band, is appended: see
    :func:`sample_cost`. ``channels_last``: the same numbers stored channels-last (the
    filter's lookups read every channel of a tap at once), written in that layout rather
    than copied into it. On a CPU (float32) OpenCV computes them (:func:`_opencv_descriptors`),
    elsewhere torch (:func:`_torch_descriptors`): the same numbers to float32 rounding. One
    image channels-last on a CPU is described by the native kernel
    (:func:`.native_descriptors.native_table`), the same numbers to float32 rounding again.
    """
    check_patch(patch, stride)
    if channels_last:
        layout = _kernel_patch(patch, int(stride), int(channels), float(blur_sigma), float(eps))
        table = native_table(images, layout, visibility_margin)
        if table is not None:
            return table
    blurred = gaussian_blur(images, blur_sigma)
    spec = _Spec(patch, int(stride), float(eps), visibility_margin, int(channels), bool(channels_last))
    if blurred.device.type == 'cpu' and blurred.dtype == torch.float32 and not blurred.requires_grad:
        return _opencv_descriptors(blurred, spec)
    return _torch_descriptors(blurred, spec)


@dataclass(frozen=True)
class _Spec:
    """What :func:`patch_descriptors` was asked for, past the blur (both implementations)."""

    patch: str
    stride: int
    eps: float
    visibility_margin: int | None
    channels: int
    channels_last: bool


def _torch_descriptors(blurred: torch.Tensor, spec: _Spec) -> torch.Tensor:
    """:func:`patch_descriptors` of blurred images in torch (CUDA, and other dtypes)."""
    reach = patch_reach(spec.patch, spec.stride)
    padded = F.pad(blurred[:, None], (reach,) * 4, mode='replicate')[:, 0]
    b, h, w = blurred.shape
    offsets = PATCH_OFFSETS[spec.patch]
    stack = torch.stack(
        [
            padded[
                :,
                reach + dy * spec.stride : reach + dy * spec.stride + h,
                reach + dx * spec.stride : reach + dx * spec.stride + w,
            ]
            for dx, dy in offsets
        ],
        dim=1,
    )
    basis = _basis(spec.patch, spec.channels, blurred.dtype, blurred.device)
    channels = basis.shape[0]
    extra = 0 if spec.visibility_margin is None else 1
    layout = torch.channels_last if spec.channels_last else torch.contiguous_format
    out = torch.empty(
        (b, channels + extra, h, w), dtype=blurred.dtype, device=blurred.device, memory_format=layout
    )
    desc = out[:, :channels]
    projected = torch.matmul(basis, stack.reshape(b, len(offsets), h * w)).reshape(b, channels, h, w)
    # (d * d).sum beats linalg.vector_norm over the channel dimension by far on CPU; the
    # division writes straight into the output (one pass, no copy first), in either layout.
    norm = torch.sqrt((projected * projected).sum(dim=1, keepdim=True) + len(offsets) * spec.eps * spec.eps)
    torch.div(projected, norm, out=desc)
    if spec.visibility_margin is not None:
        m = int(spec.visibility_margin)
        inside = out[:, channels]
        inside.zero_()
        inside[:, m : h - m, m : w - m] = 1.0
        _zero_border(desc, m)
    return out


def _zero_border(images: torch.Tensor | np.ndarray, margin: int) -> None:
    """Zero a band of ``margin`` pixels along the border of ``(..., H, W)`` images (tensors or
    arrays), in place."""
    if margin <= 0:
        return
    images[..., :margin, :] = 0.0
    images[..., -margin:, :] = 0.0
    images[..., :, :margin] = 0.0
    images[..., :, -margin:] = 0.0


@functools.lru_cache(maxsize=16)
def _kernel_patch(patch: str, stride: int, channels: int, sigma: float, eps: float) -> KernelPatch | None:
    """The layout as the native kernel reads it (:func:`zero_mean_basis` in float32, the patch's
    offsets and reach, :func:`gaussian_taps`, the norm's floor), made once per layout (None where
    it does not fit the kernel)."""
    offsets = PATCH_OFFSETS[patch]
    blur = gaussian_taps(sigma) if sigma > 0 else (1.0,)
    floor = float(np.float32(len(offsets) * eps * eps))
    rows = zero_mean_basis(patch, channels).astype(np.float32)
    return kernel_patch(rows, offsets, stride, patch_reach(patch, stride), blur, floor)


@functools.lru_cache(maxsize=16)
def _cv_kernels(patch: str, stride: int, channels: int) -> tuple[np.ndarray, ...]:
    """One correlation kernel per descriptor channel: the channel's basis row placed at the
    patch's taps (``stride`` apart) of a ``2 reach + 1`` square, zero elsewhere."""
    reach = patch_reach(patch, stride)
    basis = zero_mean_basis(patch, channels)
    kernels = []
    for row in basis:
        kernel = np.zeros((2 * reach + 1, 2 * reach + 1), dtype=np.float32)
        for weight, (dx, dy) in zip(row, PATCH_OFFSETS[patch], strict=True):
            kernel[reach + dy * stride, reach + dx * stride] = weight
        kernels.append(kernel)
    return tuple(kernels)


def _opencv_descriptors(blurred: torch.Tensor, spec: _Spec) -> torch.Tensor:
    """:func:`patch_descriptors` of blurred CPU float32 images, with OpenCV.

    Why: the depth filter describes every frame, and in torch the patch stack, its
    projection, the channel norm and the division each walk the whole image (2.3-2.8 ms at
    320x240 on one thread, the division into the channels-last output alone 1.1 ms). Here each
    channel is one ``filter2D`` of the blurred image with the basis row at the patch's taps
    (border pixels repeated, as the torch path pads), the norm is accumulated plane by plane,
    and ``merge`` interleaves the normalised planes into the channels-last layout in one pass.
    The numbers are the torch path's to float32 rounding (the sums run in another order).
    """
    kernels = _cv_kernels(spec.patch, spec.stride, spec.channels)
    b, h, w = blurred.shape
    floor = np.float32(len(PATCH_OFFSETS[spec.patch]) * spec.eps * spec.eps)
    margin = spec.visibility_margin
    planar = (
        None if spec.channels_last else np.empty((b, len(kernels) + (margin is not None), h, w), np.float32)
    )
    interleaved = []
    for i, image in enumerate(blurred.detach().numpy()):
        src = np.ascontiguousarray(image)
        planes = [
            cv2.filter2D(src, cv2.CV_32F, kernel, borderType=cv2.BORDER_REPLICATE) for kernel in kernels
        ]
        total = np.full((h, w), floor, dtype=np.float32)
        for plane in planes:
            cv2.accumulateSquare(plane, total)  # total += plane ** 2, no temporary
        inverse = np.reciprocal(np.sqrt(total, out=total), out=total)
        if margin is not None:
            _zero_border(inverse, int(margin))
            planes.append(_inside(h, w, int(margin)))
        if planar is None:  # normalised in place, interleaved by merge (its one copy)
            for plane in planes[: len(kernels)]:
                plane *= inverse
            if b == 1:
                return _interleave(planes, h, w)
            interleaved.append(cv2.merge(planes).reshape(h, w, len(planes)))
        else:  # normalised straight into the output
            for c, plane in enumerate(planes[: len(kernels)]):
                np.multiply(plane, inverse, out=planar[i, c])
            if margin is not None:
                planar[i, -1] = planes[-1]
    if planar is not None:
        return torch.from_numpy(planar)
    return torch.from_numpy(np.stack(interleaved)).permute(0, 3, 1, 2)


def _interleave(planes: list[np.ndarray], h: int, w: int) -> torch.Tensor:
    """One image's planes interleaved, ``(1, len(planes), h, w)`` channels-last, by one merge.

    Where they fit the native kernels' block (``native_cost.LANES`` floats a pixel), merged
    into such blocks (the spare channels zero) with one zero block after the last pixel: the
    kernels' descriptor table (``native_cost._channels_last``), which they read in place.

    Why: the filter's searches read every frame's descriptors through that table, and
    copying them into it cost a twentieth of the filter's frame (0.32 ms at 320x240 on one
    thread), against 0.03 ms more for merging eight planes instead of seven. The returned
    view holds the same numbers as the plain merge; only the pixel stride differs.
    """
    channels = len(planes)
    if channels > LANES:
        return torch.from_numpy(cv2.merge(planes).reshape(1, h, w, channels)).permute(0, 3, 1, 2)
    table = np.empty((h * w + 1) * LANES, np.float32)
    table[h * w * LANES :] = 0.0
    cv2.merge(planes + [_zeros(h, w)] * (LANES - channels), table[: h * w * LANES].reshape(h, w, LANES))
    # The tensor over the whole table (zero block included), then the view of its pixels.
    pixels = torch.from_numpy(table)[: h * w * LANES].view(1, h, w, LANES)
    return pixels.permute(0, 3, 1, 2)[:, :channels]


@functools.lru_cache(maxsize=8)
def _zeros(height: int, width: int) -> np.ndarray:
    """A zero plane (read-only, made once): the spare channels of a pixel block."""
    zeros = np.zeros((height, width), dtype=np.float32)
    zeros.flags.writeable = False
    return zeros


@functools.lru_cache(maxsize=8)
def _inside(height: int, width: int, margin: int) -> np.ndarray:
    """The visibility channel: 1 inside the ``margin`` band, 0 in it (read-only, made once)."""
    inside = np.zeros((height, width), dtype=np.float32)
    inside[margin : height - margin, margin : width - margin] = 1.0
    inside.flags.writeable = False
    return inside
