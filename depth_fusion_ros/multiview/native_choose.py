"""A frame's geometry for the filter's keyframe and the rows it searches, in one native pass
(``filter_choose.c``).

Before its searches, each frame projects every candidate pixel of the keyframe
(:func:`.filter_geometry.frame_geometry`) and picks the rows worth a search
(:func:`.filter_frame_update.choose_rows`): some sixty torch ops over tens of thousands of
pixels, about a tenth of a filter frame on one thread. The kernel gives the same geometry, the
same rows and the same count of first attempts, bit for bit, in one pass. On CUDA, or where
it cannot be built (``native_build.load_native``), the torch code runs.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..native_build import load_native
from .filter_geometry import FrameGeometry, frame_projection, image_centre
from .filter_keyframe import FilterKeyframe

if TYPE_CHECKING:
    from .filter import DepthFilter


def native_choose(
    filt: DepthFilter, key: FilterKeyframe, T_fk: np.ndarray, baseline: float, only: torch.Tensor | None
) -> tuple[FrameGeometry, torch.Tensor, float] | None:
    """``(frame_geometry(...), *choose_rows(...))`` of this frame in the kernel (the first
    attempts counted in ``key.attempts`` as there), or ``None`` (nothing done) where it does
    not apply: not a CPU, the keyframe's tensors not of the filter's types, or no kernel here."""
    if not _applies(key, only):
        return None
    lib = _library()
    if lib is None:
        return None
    c, cam = filt.config, filt.camera
    h, b = frame_projection(cam, T_fk, key.us.device)
    h = h.contiguous()
    m = int(key.us.numel())
    a, j, along = torch.empty((3, m)), torch.empty(m), torch.empty(m)
    visible = torch.empty(m, dtype=torch.bool)
    rows = torch.empty(m, dtype=torch.long)
    counts = torch.zeros(3, dtype=torch.long)
    cu, cv = image_centre(cam)
    with_pose = c.pose_sigma != 0.0
    seeding = c.seeds_at(baseline / filt._scene)
    st = key.state
    pixels = (key.us, key.vs, st.mu, st.var, key.prior)
    lib.filter_choose(
        m, *(t.data_ptr() for t in pixels), None if only is None else only.data_ptr(),
        key.attempts.data_ptr(), key.grad.data_ptr(), h.data_ptr(), *b,
        cu, cu - filt.margin, cv, cv - filt.margin, float(c.min_epipolar_gradient), float(c.min_information),
        float(c.pixel_sigma), float(c.pose_sigma / baseline) if with_pose else 0.0, int(with_pose),
        int(seeding), int(c.seed_attempts),
        a.data_ptr(), j.data_ptr(), along.data_ptr(), visible.data_ptr(), rows.data_ptr(), counts.data_ptr(),
    )  # fmt: skip
    n_rows, n_estimates, n_seen = (int(v) for v in counts)
    seen = n_seen / n_estimates if n_estimates > 0 else 1.0
    return FrameGeometry(a, b, j, along, visible), rows[:n_rows], seen


def _applies(key: FilterKeyframe, only: torch.Tensor | None) -> bool:
    st = key.state
    floats = (key.us, key.vs, st.mu, st.var, key.grad)
    m = key.us.shape  # the kernel reads M entries of every per-pixel array
    return (
        key.us.device.type == 'cpu'
        and all(t.dtype == torch.float32 and t.is_contiguous() for t in floats)
        and all(t.shape == m for t in (key.vs, st.mu, st.var, key.prior, key.attempts))
        and key.grad.shape == (2, *m)
        and key.prior.dtype == torch.bool
        and key.prior.is_contiguous()
        and key.attempts.dtype == torch.long
        and key.attempts.is_contiguous()
        and (only is None or (only.dtype == torch.bool and only.is_contiguous() and only.shape == m))
    )


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now; whether it will be used."""
    return _library() is not None


def _library() -> ctypes.CDLL | None:
    p, i64, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    inputs = [i64, p, p, p, p, p, p, p, p, p]  # M, the pixels, attempts, grad, h
    numbers = [f, f, f, f, f, f, f, f, f, f, f, i, i, i64]  # b, the image's bounds, the tests
    outputs = [p, p, p, p, p, p]  # a, j, along, visible, rows, counts
    signature = {'filter_choose': inputs + numbers + outputs}
    return load_native(Path(__file__).with_name('filter_choose.c'), signature)
