"""One posed frame's measurements for the filter's keyframe: choose, search, fuse, in place.

Step 2 of ``filter.py``'s flow. Cheap per-pixel tests on every keyframe pixel first pick
the rows the frame can teach something (:func:`choose_rows`); only those are searched
along their epipolar line (:func:`search_rows`, in buckets by interval length), a row's first
measurement is checked once more at one sample a pixel (``filter_first_check``), and the
matches are fused (``filter_matches``: the Gaussian x uniform update of the rows that matched),
so the frame's cost follows the pixels that still need it, not the candidate count.
On a CPU each step is a native pass with the same numbers (``native_choose``, ``native_bracket``,
``native_rows``: the searches, their tests and the check; ``native_apply``); the torch code
here is the reference, and runs on CUDA.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..true_indices import true_indices
from .filter_bracket import bracket_seeds
from .filter_buckets import bucket_members, search_buckets
from .filter_first_check import check_first_matches
from .filter_geometry import FrameGeometry, frame_geometry, grid_rows_in_place, row_motion
from .filter_keyframe import FilterKeyframe
from .filter_matches import Matches, apply_matches, measurement_variance
from .filter_rows import ChosenRows
from .filter_search import SearchResult
from .native_choose import native_choose
from .native_rows import native_search_rows

if TYPE_CHECKING:
    from .filter import DepthFilter


def update_frame(
    filt: DepthFilter,
    key: FilterKeyframe,
    desc: torch.Tensor,
    T_fk: np.ndarray,
    only: torch.Tensor | None = None,
) -> float:
    """One frame's measurements for the pixels of ``key`` it can teach something, in place.

    Cheap per-pixel tests on every pixel first (:func:`choose_rows`), then the searches and
    the update on the chosen rows only, scattered back: the frame's cost follows the pixels
    that still need it, not the candidate count. Returns the fraction of the estimates
    that project into the frame (the keyframe-switch test), from the same projection.
    ``only``: the new keyframe's first measurements at a switch (its stages are the
    ``seed`` ones of the filter's ``clock``).
    """
    prefix = 'seed ' if only is not None else ''
    left = filt.clock.switch(prefix + 'selection')
    try:
        return _update_rows(filt, key, desc, T_fk, only, prefix)
    finally:
        filt.clock.switch(left)


def _update_rows(
    filt: DepthFilter,
    key: FilterKeyframe,
    desc: torch.Tensor,
    T_fk: np.ndarray,
    only: torch.Tensor | None,
    prefix: str,
) -> float:
    """:func:`update_frame`'s work; ``prefix`` names its stages."""
    c = filt.config
    rho_min, rho_max = filt.rho_range
    st = key.state
    baseline = max(float(np.linalg.norm(T_fk[:3, 3])), 1e-9)
    chosen = native_choose(filt, key, T_fk, baseline, only)  # the same, in one pass on a CPU
    if chosen is None:
        geo = frame_geometry(key, filt.camera, T_fk, filt.margin)
        rows, seen = choose_rows(filt, key, geo, baseline, only)
    else:
        geo, rows, seen = chosen
    if rows.numel() == 0:
        return seen
    # Everything below runs on the chosen rows only (index_select: several times faster
    # on CPU than advanced indexing).
    pick = lambda t: t.index_select(0, rows)  # noqa: E731
    a_r, j_r = geo.a.index_select(1, rows), pick(geo.j)
    mu_r, var_r, f_r = pick(st.mu), pick(st.var), ~pick(key.prior)
    # The rows without a prior, once: the whole-range bounds, the search's spans and the
    # first measurements are index ops on these few rows instead of where over all rows
    # (torch.where is several times slower than arithmetic on CPU).
    seeds = true_indices(f_r)
    floor = c.min_search_px / torch.clamp(j_r, min=1e-9)
    half = torch.maximum(c.search_sigmas * torch.sqrt(var_r), floor)
    lo = torch.clamp(mu_r - half, rho_min, rho_max).index_fill_(0, seeds, rho_min)
    hi = torch.clamp(mu_r + half, rho_min, rho_max).index_fill_(0, seeds, rho_max)
    bracketed = bracket_seeds(filt, key, rows, seeds, f_r, a_r, geo.b, lo, hi)
    filt.clock.switch(prefix + 'search')
    # On a CPU the searches, the tests below and the first-measurement check in one native pass
    # (native_rows: the same numbers); elsewhere, or with a test's search, the torch code.
    chosen = ChosenRows(rows, a_r, geo, lo, hi, j_r, f_r, seeds, bracketed)
    searched = native_search_rows(filt, key, desc, chosen)
    if searched is None:
        x, j_x, cost, valid = _search_and_test(filt, key, desc, chosen, prefix)
    else:  # its stage is the search's, the first-measurement check's searches included
        x, j_x, cost, valid = searched
        filt.clock.switch(prefix + 'update')
    apply_matches(filt, key, Matches(rows, x, j_x, cost, f_r), valid, baseline)
    return seen


def _search_and_test(
    filt: DepthFilter, key: FilterKeyframe, desc: torch.Tensor, chosen: ChosenRows, prefix: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The searches of the chosen rows and the tests of their matches in torch: ``(x, j_x, cost,
    valid)`` per row (``native_rows`` gives the same in one pass on a CPU)."""
    rows, a_r, geo, lo, hi, _, _, _, bracketed = chosen
    rho_min, rho_max = filt.rho_range
    # Through the filter (its module's search_interval, read at the call: tests count the searches).
    x, cost, valid = search_rows(filt, key, desc, chosen, filt.search)
    filt.clock.switch(prefix + 'update')
    # The epipolar motion at the match: the bracket's edge test and the measurement
    # variance (only read where the match is valid, so one evaluation at x serves both).
    j_x = row_motion(a_r, geo.b, x)
    if bracketed is not None:
        # A bracket's best match on its edge: the minimum lies outside, not a measurement.
        inside = ((x - lo) * j_x >= 0.5) & ((hi - x) * j_x >= 0.5)
        valid &= ~bracketed | inside
    valid &= (x >= rho_min) & (x <= rho_max)
    valid &= j_x > 1e-6
    valid = check_first_matches(filt, key, rows, desc, a_r, geo, x, j_x, cost, valid)
    return x, j_x, cost, valid


def choose_rows(
    filt: DepthFilter, key: FilterKeyframe, geo: FrameGeometry, baseline: float, only: torch.Tensor | None
) -> tuple[torch.Tensor, float]:
    """Rows this frame searches, and the fraction of the estimates it sees.

    LSD-SLAM: only where the gradient has a component along the epipolar line. REMODE:
    converged pixels this frame cannot improve are left alone. Whole-range searches only
    from frames with ``seed_parallax`` and ``seed_attempts`` left. Pixels without a prior
    are searched from the middle of the range (``mu`` holds it:
    ``filter_new_keyframe.fresh_state``), so their projection only gives the epipolar
    direction.
    """
    c = filt.config
    st = key.state
    fresh = ~key.prior
    estimates = key.prior  # a measured, carried or filled prior
    want = (geo.along >= c.min_epipolar_gradient) & (fresh | geo.visible)
    want &= fresh | (st.var >= c.min_information * measurement_variance(c, st.mu, geo.j, baseline))
    seeding = c.seeds_at(baseline / filt._scene)
    if seeding:
        want &= estimates | (key.attempts < c.seed_attempts)
    else:
        want &= estimates
    if only is not None:
        want &= only
    seeds = want & fresh
    key.attempts += seeds.long()
    n_estimates = float(estimates.sum())
    seen = float((geo.visible & estimates).sum()) / n_estimates if n_estimates > 0 else 1.0
    return true_indices(want), seen


def search_rows(
    filt: DepthFilter,
    key: FilterKeyframe,
    desc: torch.Tensor,
    chosen: ChosenRows,
    search: Callable[..., SearchResult],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Search each chosen row in ``[lo, hi]``, in buckets by sample count (``bucket_members``).

    Returns the match ``x``, its cost and whether it passed ``max_cost`` (and, in the
    buckets with a distinctiveness test, ``min_distinctiveness``; with
    ``reject_edge_minima``, lay inside its interval), per row. ``search``:
    ``filter_search.search_interval``, passed in by the filter.
    """
    c = filt.config
    rows, a_r, geo, lo, hi, j_r, fresh, seeds, _ = chosen
    # Interval length in px: to first order at the prior mean for an estimate (as the
    # +-2 px floor is set); a whole-range search takes the larger motion of its two ends.
    span = j_r * (hi - lo)
    if seeds.numel() > 0:  # the rows of ``fresh``
        a_s, lo_s, hi_s = a_r.index_select(1, seeds), lo.index_select(0, seeds), hi.index_select(0, seeds)
        ends = torch.maximum(row_motion(a_s, geo.b, lo_s), row_motion(a_s, geo.b, hi_s))
        span.index_copy_(0, seeds, ends * (hi_s - lo_s))
    # Rows sorted by bucket once: each bucket is then a slice (views, no gather per bucket),
    # and the results go back in one scatter.
    members = bucket_members(span, fresh, c)
    order = torch.cat(members)  # a counting sort: torch.argsort is several times slower on CPU
    counts = [int(m.numel()) for m in members]
    desc_o = key.key_desc.index_select(1, rows.index_select(0, order))
    lo_o, hi_o = lo.index_select(0, order), hi.index_select(0, order)
    # The rays normalised once for the frame, not once per bucket.
    a_o, b_o = grid_rows_in_place(a_r.index_select(1, order), geo.b, filt.camera.width, filt.camera.height)
    xs, costs, goods = [], [], []
    start = 0
    for (samples, refine, distinct), n in zip(search_buckets(c), counts, strict=True):
        if n == 0:
            continue
        stop = start + n
        found = search(
            desc_o[:, start:stop],
            desc,
            (a_o[:, start:stop], b_o),
            lo_o[start:stop],
            hi_o[start:stop],
            samples,
            refine,
            filt._chunk_elements,
            with_distinctiveness=distinct,
            reject_edges=c.reject_edge_minima,
        )
        good = found.ok & (found.cost <= c.max_cost)
        if distinct:
            good &= found.distinct >= c.min_distinctiveness
        xs.append(found.rho)
        costs.append(found.cost)
        goods.append(good)
        start = stop
    x = torch.empty_like(lo).scatter_(0, order, torch.cat(xs))
    cost = torch.empty_like(lo).scatter_(0, order, torch.cat(costs))
    valid = torch.empty_like(fresh).scatter_(0, order, torch.cat(goods))
    return x, cost, valid
