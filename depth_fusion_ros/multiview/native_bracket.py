"""The seed bracket of a frame's new pixels in one native pass (``filter_bracket.c``).

:func:`.filter_bracket.bracket_seeds` narrows the first search of each new pixel next to
measured ones to its neighbours' inverse depths: in torch a gather of each pixel's window
(49 entries at the default radius of 3), a masked minimum and maximum, and the interval's ends at
the epipolar motion there, some twenty small ops a frame. The kernel gives the same intervals
bit for bit in one loop per pixel. On CUDA, or where it cannot be built
(``native_build.load_native``), the torch code runs.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ..native_build import load_native
from .filter_keyframe import FilterKeyframe, padded_maps

if TYPE_CHECKING:
    from .filter import DepthFilter


def native_bracket(
    filt: DepthFilter,
    key: FilterKeyframe,
    rows: torch.Tensor,
    seeds: torch.Tensor,
    a_r: torch.Tensor,
    b: tuple[float, float, float],
    lo: torch.Tensor,
    hi: torch.Tensor,
) -> tuple[bool, torch.Tensor | None]:
    """``(True, bracket_seeds's result)`` with ``lo`` and ``hi`` narrowed in place as there (None
    where no row was bracketed: the same intervals, and nothing for the edge test to do), or
    ``(False, None)``, nothing done, where the kernel does not apply: not a CPU, tensors not of
    the filter's types, or no kernel here."""
    if not _applies(key, rows, seeds, a_r, lo, hi):
        return False, None
    lib = _library()
    if lib is None:
        return False, None
    padded_flat, padded_rows = padded_maps(filt, key)
    c = filt.config
    r = int(c.seed_radius)
    n = int(rows.numel())
    use = torch.zeros(n, dtype=torch.bool)
    count = torch.zeros(1, dtype=torch.long)
    lib.filter_bracket(
        int(seeds.numel()), seeds.data_ptr(), rows.data_ptr(),
        key.attempts.data_ptr(), key.updates.data_ptr(), key.state.mu.data_ptr(),
        padded_flat.data_ptr(), padded_rows.data_ptr(), int(key.flat.numel()),
        r, filt.camera.width + 2 * r, a_r.data_ptr(), a_r.stride(0), *b, 2.0 * c.min_search_px,
        *filt.rho_range, lo.data_ptr(), hi.data_ptr(), use.data_ptr(), count.data_ptr(),
    )  # fmt: skip
    return True, (use if int(count[0]) > 0 else None)


def _applies(
    key: FilterKeyframe,
    rows: torch.Tensor,
    seeds: torch.Tensor,
    a_r: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
) -> bool:
    m, n = key.flat.shape, rows.shape
    longs = (rows, seeds, key.attempts, key.updates)
    return (
        rows.device.type == 'cpu'
        and all(t.dtype == torch.long and t.is_contiguous() for t in longs)
        and all(t.shape == m for t in (key.attempts, key.updates, key.state.mu, key.us, key.vs))
        and key.state.mu.dtype == torch.float32
        and key.state.mu.is_contiguous()
        and a_r.dtype == torch.float32
        and a_r.shape == (3, *n)
        and a_r.stride(-1) == 1
        and all(t.dtype == torch.float32 and t.is_contiguous() and t.shape == n for t in (lo, hi))
        and seeds.dim() == 1
    )


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now; whether it will be used."""
    return _library() is not None


def _library() -> ctypes.CDLL | None:
    p, i64, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    inputs = [i64, p, p, p, p, p, p, p, i64, i, i64, p, i64]  # S, the rows and maps, m, r, wp, a
    numbers = [f, f, f, f, f, f]  # b, the pad, the range
    outputs = [p, p, p, p]  # lo, hi, use, count
    signature = {'filter_bracket': inputs + numbers + outputs}
    return load_native(Path(__file__).with_name('filter_bracket.c'), signature)
