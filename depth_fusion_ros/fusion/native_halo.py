"""The silhouette-halo test of every point in one native pass (``halo_test.c``).

:func:`.occlusion.halo_points` reads, for each multi-view point, seven samples of the gradient
magnitude along the gradient, four of the single-view log depth and, for the candidates, eighteen
of the points beyond; in numpy that is a few dozen whole-array operations over the 16-20
thousand points of a 320x240 keyframe, 6-12 ms, a tenth of the fusion node's keyframe. The
kernel does the five steps point by point with numpy's operations in their order (OpenCV's
bilinear read included): the same halos bit for bit. Where it cannot be built
(``native_build.load_native``), numpy runs.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..native_build import kernel_threads, load_native

#: Points below which one thread tests them all (the hand-over costs more).
THREAD_MIN_POINTS = 4096
#: The largest search half-length and the most steps beyond the kernel holds (``halo_test.c``).
MAX_SEARCH_PX = 32
MAX_BEYOND_STEPS = 64


class HaloShape(NamedTuple):
    """The test's geometry, ``occlusion.py``'s constants: handed to the kernel at each call so
    that they are written in one place."""

    search_px: int
    side_px: float
    near_share: float
    beyond_px: tuple[int, int]

    def fits(self) -> bool:
        """Whether the kernel holds this geometry (else numpy tests the points)."""
        first, last = self.beyond_px
        return 1 <= self.search_px <= MAX_SEARCH_PX and 0 <= first <= last < first + MAX_BEYOND_STEPS


def native_halo(
    magnitude: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    filled: np.ndarray,
    log_points: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    log_m: np.ndarray,
    scale: float,
    min_step: float,
    shape: HaloShape,
) -> np.ndarray | None:
    """Which points (``rows``, ``cols``, multi-view log depth ``log_m``) sit in a halo, as a bool
    array over them, or None where the kernel cannot run here or does not hold ``shape``.
    ``magnitude``, ``gx``, ``gy``: the blurred keyframe's gradient (``occlusion._gradients``);
    ``filled``: the single-view log depth, its holes filled; ``log_points``: ``log_m`` at the
    points, NaN elsewhere; ``scale``: the points' median log ratio to the single view."""
    lib = _library()
    if lib is None or not shape.fits():
        return None
    h, w = magnitude.shape
    planes = [np.ascontiguousarray(a, dtype=np.float32) for a in (magnitude, gx, gy, filled, log_points)]
    if any(p.shape != (h, w) for p in planes):
        raise ValueError(f'halo test planes differ in size: {[p.shape for p in planes]}')
    rows64 = np.ascontiguousarray(rows, dtype=np.int64)
    cols64 = np.ascontiguousarray(cols, dtype=np.int64)
    values = np.ascontiguousarray(log_m, dtype=np.float32)
    n = len(values)
    out = np.zeros(n, dtype=np.uint8)
    first, last = (int(v) for v in shape.beyond_px)
    lib.halo_test(
        h, w, *(p.ctypes.data for p in planes), n, rows64.ctypes.data, cols64.ctypes.data, values.ctypes.data,
        float(scale), float(min_step), int(shape.search_px), float(shape.side_px), float(shape.near_share),
        first, last, out.ctypes.data, kernel_threads(n, THREAD_MIN_POINTS),
    )  # fmt: skip
    return out.view(bool)


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now; whether it will be used."""
    return _library() is not None


def _library() -> ctypes.CDLL | None:
    p, i64, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    planes = [p, p, p, p, p]  # magnitude, gx, gy, filled, log_points
    geometry = [i, f, f, i, i]  # search_px, side_px, near_share, the span beyond
    signature = {'halo_test': [i64, i64, *planes, i64, p, p, p, f, f, *geometry, p, i]}
    return load_native(Path(__file__).with_name('halo_test.c'), signature)
