"""A frame's descriptors written as the native kernels' table in one native pass
(``describe_table.c``).

The temporal filter describes every posed frame and its searches read the descriptors from a
table of :data:`.native_cost.LANES` floats a pixel. With OpenCV (``descriptors._opencv_descriptors``)
that is a blur, a ``filter2D`` a channel, the norm plane by plane, a product a channel and a
merge into the table, about 1 ms at 320x240 on one thread, a tenth of the filter's frame. The
kernel blurs, projects, normalises and interleaves row by row in one pass. Its numbers are
OpenCV's to float32 rounding (the same sums in another order), so the filter's later choices
may differ in the last bits from a run without the kernel. On CUDA, for planar descriptors,
several images, or where it cannot be built (``native_build.load_native``), OpenCV or torch
describes as before.
"""

from __future__ import annotations

import ctypes
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..native_build import kernel_threads, load_native
from .native_cost import LANES

#: Below this many pixels one thread describes the image (a 320x240 frame: 76800).
THREAD_MIN_PIXELS = 1 << 16
#: The most taps a patch may have (``describe_table.c``'s TAPS: the 3x3 box).
TAPS = 9


class KernelPatch(NamedTuple):
    """A patch layout as the kernel reads it, made once per layout (``descriptors``): the basis
    (``channels`` rows) padded with zeros to (:data:`LANES`, :data:`TAPS`) float32 (the kernel
    always projects all of them; a zero row is a zero channel), the taps' pixel offsets ``dx``,
    ``dy`` (:data:`TAPS` of them, the unused ones at the centre) and their ``reach``, the blur's
    taps and the norm's ``floor`` (``P eps^2``)."""

    channels: int
    basis: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    reach: int
    blur: np.ndarray
    floor: float


def kernel_patch(
    rows: np.ndarray,
    offsets: tuple[tuple[int, int], ...],
    stride: int,
    reach: int,
    blur: tuple[float, ...],
    floor: float,
) -> KernelPatch | None:
    """The layout of ``rows`` (K, P) at the patch ``offsets`` (``stride`` px apart, at most
    ``reach`` px out) with the blur's taps ``blur`` (one tap of 1: none), or None where it does not
    fit a block."""
    k, p = rows.shape
    if k > LANES or p > TAPS or p != len(offsets):
        return None
    basis = np.zeros((LANES, TAPS), dtype=np.float32)
    basis[:k, :p] = rows
    dx = np.zeros(TAPS, dtype=np.int32)
    dy = np.zeros(TAPS, dtype=np.int32)
    dx[:p] = [ox * stride for ox, _ in offsets]
    dy[:p] = [oy * stride for _, oy in offsets]
    taps = np.asarray(blur, dtype=np.float32)
    for a in (basis, dx, dy, taps):
        a.flags.writeable = False
    return KernelPatch(k, basis, dx, dy, int(reach), taps, float(floor))


def native_table(images: torch.Tensor, patch: KernelPatch | None, margin: int | None) -> torch.Tensor | None:
    """The descriptors ``(1, K [+ 1], H, W)`` of one grey ``(1, H, W)`` image as a view of the
    kernels' table (what ``descriptors._interleave`` returns), or None where the kernel does not
    apply (not one CPU float32 image, too many channels for a block, no kernel here)."""
    if patch is None:
        return None
    channels = patch.channels + (margin is not None)
    if not _applies(images, channels):
        return None
    lib = _library()
    if lib is None:
        return None
    _, h, w = images.shape
    image = images.detach().contiguous()
    table = torch.empty((h * w + 1) * LANES, dtype=torch.float32)
    lib.describe_table(
        h, w, image.data_ptr(), len(patch.blur), patch.blur.ctypes.data, patch.dx.ctypes.data,
        patch.dy.ctypes.data, patch.reach, patch.channels, patch.basis.ctypes.data, patch.floor,
        -1 if margin is None else int(margin), table.data_ptr(), kernel_threads(h * w, THREAD_MIN_PIXELS),
    )  # fmt: skip
    if math.isnan(float(table[0])):
        raise MemoryError('describe_table: no memory for its working planes')
    pixels = table[: h * w * LANES].view(1, h, w, LANES)
    return pixels.permute(0, 3, 1, 2)[:, :channels]


def _applies(images: torch.Tensor, channels: int) -> bool:
    return (
        images.device.type == 'cpu'
        and images.dtype == torch.float32
        and images.dim() == 3
        and images.shape[0] == 1
        and not images.requires_grad
        and channels <= LANES
        and images.shape[1] > 0
        and images.shape[2] > 0
    )


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now; whether it will be used."""
    return _library() is not None


def _library() -> ctypes.CDLL | None:
    p, i64, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    inputs = [i64, i64, p, i, p, p, p, i, i, p, f, i]  # h, w, image, blur, taps, reach, basis, floor, margin
    signature = {'describe_table': [*inputs, p, i]}  # the table, threads
    return load_native(Path(__file__).with_name('describe_table.c'), signature)
