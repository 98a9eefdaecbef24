"""One frame's matches into the filter's keyframe in two native passes (``filter_apply.c``).

After a frame's searches, :func:`.filter_matches.apply_matches` updates the keyframe's state
row by row: the Gaussian x uniform update of the rows that measured, the first measurements,
the outlier votes and the resets. In torch that is some sixty small ops a frame (about a
tenth of a filter frame on one thread, `torch.profiler`), each a dispatch and a pass over a
few thousand rows. The kernel makes the same state, bit for bit: one pass before the
exponential and the square root and one after them. Those two stay torch's (``torch.exp``,
``torch.sqrt``: MKL's vector functions in this torch, within an ulp of the exact result but
not always the nearest float, so only the same call gives the same numbers). On CUDA, or
where it cannot be built (``native_build.load_native``), the torch code runs.
"""

from __future__ import annotations

import ctypes
import math
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ..native_build import load_native
from ..true_indices import true_indices
from .filter_keyframe import FilterKeyframe, no_estimate

if TYPE_CHECKING:
    from .filter import DepthFilter
    from .filter_matches import Matches


def native_apply_matches(
    filt: DepthFilter, key: FilterKeyframe, matches: Matches, valid: torch.Tensor, baseline: float
) -> bool:
    """:func:`.filter_matches.apply_matches` on a CPU in the kernel, in place; ``False`` (and
    nothing done) where it does not apply: not a CPU, state or matches not float32 / int64 /
    bool as the filter makes them, or no kernel here."""
    st = key.state
    floats = (st.mu, st.var, st.a, st.b, key.cost)
    per_row = (matches.x, matches.j_x, matches.cost)
    applies = (
        matches.rows.device.type == 'cpu'
        and matches.rows.dtype == torch.long
        and matches.fresh.dtype == torch.bool
        and valid.dtype == torch.bool
        and all(t.shape == matches.rows.shape for t in (*per_row, matches.fresh, valid))
        and all(t.dtype == torch.float32 and t.is_contiguous() for t in floats)
        and all(t.dtype == torch.float32 for t in per_row)
        and key.updates.dtype == torch.int64
        and key.prior.dtype == torch.bool
        and key.updates.is_contiguous()
        and key.prior.is_contiguous()
    )
    lib = _library() if applies else None
    if lib is None:
        return False
    c = filt.config
    rows = matches.rows.contiguous()
    x, j_x, cost = (t.contiguous() for t in (matches.x, matches.j_x, matches.cost))
    fresh = matches.fresh.contiguous()
    meas = true_indices(valid)
    votes = true_indices(~fresh & ~valid)
    n = int(meas.numel())
    tau2 = torch.empty(n, dtype=torch.float32)
    exponent = torch.empty(n, dtype=torch.float32)
    spread = torch.empty(n, dtype=torch.float32)
    with_pose = c.pose_sigma != 0.0
    pose_factor = float(c.pose_sigma / baseline) if with_pose else 0.0
    state = [t.data_ptr() for t in (st.mu, st.var, st.a, st.b, key.updates, key.prior, key.cost)]
    lib.filter_measure_exponent(
        rows.data_ptr(), meas.data_ptr(), n, x.data_ptr(), j_x.data_ptr(), *state[:2],
        float(c.pixel_sigma), pose_factor, int(with_pose), 2.0 * math.pi,
        tau2.data_ptr(), exponent.data_ptr(), spread.data_ptr(),
    )  # fmt: skip
    gaussian, root = torch.exp(exponent), torch.sqrt(spread)  # torch's own: see the module
    lo, hi = filt.rho_range
    none_mu, none_var, init_a, init_b = no_estimate(filt)[:4]  # a and b: also a first measurement's
    lib.filter_measure_finish(
        rows.data_ptr(), meas.data_ptr(), n, x.data_ptr(), cost.data_ptr(), fresh.data_ptr(),
        tau2.data_ptr(), gaussian.data_ptr(), root.data_ptr(), votes.data_ptr(), int(votes.numel()),
        *state, float(hi - lo), none_mu, none_var, init_a, init_b, float(c.min_inlier_ratio),
    )  # fmt: skip
    return True


def prepare() -> bool:
    """Build (first run on this machine) or load the kernel now; whether it will be used."""
    return _library() is not None


def _library() -> ctypes.CDLL | None:
    p, i64, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    signature = {
        'filter_measure_exponent': [p, p, i64, p, p, p, p, f, f, i, f, p, p, p],
        'filter_measure_finish': [p, p, i64, p, p, p, p, p, p, p, i64, p, p, p, p, p, p, p, f, f, f, f, f, f],
    }
    return load_native(Path(__file__).with_name('filter_apply.c'), signature)
