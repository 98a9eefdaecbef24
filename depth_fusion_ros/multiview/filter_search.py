"""Short epipolar search of keyframe pixels in one new frame, each within its own interval.

The sweep (``semidense.py``) searches every pixel over the whole inverse-depth range in
``n`` neighbours at once. The filter knows, per pixel, where the answer should be (its prior
mean +- a few standard deviations), so one frame is searched over a short interval: a few
samples per pixel instead of tens, and one frame instead of four. That is what makes an
update per posed frame affordable. The cost is the sweep's (``cost_volume.sample_cost``:
``1 - ZNCC`` of the same patch descriptors) on a per-pixel grid of inverse depths
``lo + (hi - lo) t``, then a finer grid around the best sample and a parabola, as the sweep.
On a CPU a native kernel does a bucket's whole search per row (``native_cost.native_frame_search``:
the same numbers); the torch code below is the reference, and runs on CUDA.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from ..true_indices import true_indices
from .cost_volume import EpipolarRays, rows_per_chunk
from .native_cost import native_frame_cost, native_frame_search


@dataclass
class SearchResult:
    """Per pixel: refined inverse depth, its cost, the second-best ratio and whether it is usable."""

    rho: torch.Tensor
    cost: torch.Tensor
    distinct: torch.Tensor
    ok: torch.Tensor


def _distinctiveness(cost: torch.Tensor, best: torch.Tensor, c1: torch.Tensor) -> torch.Tensor:
    """Modified second-best ratio ``1 - c1 / c2`` over local minima more than one sample away.

    ``cost`` is samples-first (S, R). ``c2`` is the lowest local minimum outside the best
    sample and its two neighbours, or the largest finite cost when there is none (a single
    basin). A dozen whole-tensor ops (two comparisons between neighbouring samples, a
    scatter for the exclusion): this runs on every whole-range search, where the sampling
    itself is not much more.
    """
    inf = math.inf
    # A local minimum is no higher than either neighbour (beyond the ends: inf, which every
    # cost but NaN passes, and a NaN fails its other comparison anyway): compared between
    # the samples themselves, without a padded copy. 1.0 / 0.0 rather than bool: comparisons
    # into floats and arithmetic with them are several times cheaper on CPU than with bool.
    is_min = torch.empty_like(cost)
    torch.le(cost[:-1], cost[1:], out=is_min[:-1])
    is_min[-1] = 1.0
    is_min[1:].mul_(torch.le(cost[1:], cost[:-1], out=torch.empty_like(cost[1:])))
    near = (best[None, :] + torch.arange(-1, 2, device=cost.device)[:, None]).clamp_(0, cost.shape[0] - 1)
    # Costs are > 0 (frame_cost), so dividing by ``is_min`` sends the other samples to inf
    # (cheaper on CPU than masked_fill; amin / amax skip the indices min / max compute).
    c2 = (cost / is_min).scatter_(0, near, inf).amin(dim=0)
    # A single basin (no other minimum): the largest finite cost instead, for those rows only.
    # Costs are >= 0, so -1 stands for "no finite cost" (the ratio is then 0, as c1 is inf).
    single = true_indices(~torch.isfinite(c2))
    if single.numel() > 0:
        largest = torch.nan_to_num(cost.index_select(1, single), posinf=-1.0).amax(dim=0)
        c2.index_copy_(0, single, largest)
    return torch.clamp(1.0 - c1 / torch.clamp(c2, min=1e-6), 0.0, 1.0)


def frame_cost(
    key_desc: torch.Tensor, frame_desc: torch.Tensor, rays: EpipolarRays, rho: torch.Tensor
) -> torch.Tensor:
    """``1 - ZNCC`` (R, S) against one frame at inverse depths ``rho`` (R, S); ``inf`` where the
    frame does not see the sample (its soft visibility below 0.5).

    ``cost_volume.sample_cost`` for a single neighbour (same numbers), without the sum over
    neighbours: one ``grid_sample`` and one contraction over the descriptor channels, the
    rest in place. The search works samples-first (:func:`_frame_cost`); this rows-first
    wrapper is the sweep's layout, for comparison.
    """
    a, b = rays._normalised()
    return _frame_cost(key_desc, frame_desc, a[0].T.contiguous(), b[0], rho.T.contiguous()).T


def _grid(a: torch.Tensor, b: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """``EpipolarRays.grid`` (1, S, R, 2) of one frame from its normalised rows ``a`` (3, R) and
    ``b`` (3,) at inverse depths ``rho`` (S, R), normalised once per search instead of once per
    lookup."""
    w = torch.addcmul(a[2], rho, b[2]).clamp_(min=1e-4)
    # Both coordinates in one product and one division, coordinate-first; grid_sample reads
    # the (1, S, R, 2) view of it as well as a contiguous grid (same numbers, 2 ops fewer).
    out = torch.addcmul(a[:2, None, :], rho, b[:2, None, None]).div_(w)
    return out.permute(1, 2, 0)[None]


def _frame_cost(
    key_desc: torch.Tensor, frame_desc: torch.Tensor, a: torch.Tensor, b: torch.Tensor, rho: torch.Tensor
) -> torch.Tensor:
    """Samples-first cost (S, R): rows ``a`` (3, R), ``rho`` (S, R), ``key_desc`` (C, R).

    On a CPU the native kernel computes it (``native_cost.py``: the same numbers in one pass);
    elsewhere, or where that cannot run, :func:`_frame_cost_torch`.
    """
    cost = native_frame_cost(key_desc, frame_desc, a, b, rho)
    return cost if cost is not None else _frame_cost_torch(key_desc, frame_desc, a, b, rho)


def _frame_cost_torch(
    key_desc: torch.Tensor, frame_desc: torch.Tensor, a: torch.Tensor, b: torch.Tensor, rho: torch.Tensor
) -> torch.Tensor:
    """:func:`_frame_cost` in torch ops (any device).

    Samples-first because the per-row factors (the rows' projections, their descriptors)
    then broadcast along the contiguous rows: on CPU every elementwise op runs vectorised over
    R instead of over S (6-32) at a time, and ``grid_sample`` is as fast (rows come in raster
    order, so neighbouring outputs still read neighbouring pixels).
    """
    channels, samples = key_desc.shape[0], rho.shape[0]
    sampled = _lookup(frame_desc, _grid(a, b, rho))
    planes, keys = sampled.unbind(1), key_desc.unbind(0)  # one op each instead of a select per channel
    count = planes[channels]
    zncc = planes[0] * keys[0]
    for c in range(1, channels):
        zncc.addcmul_(planes[c], keys[c])
    # (count - zncc + 1e-3) / (count + 1e-3), and inf where the frame does not see the sample:
    # the numerator is > 0 (|zncc| <= count for the normalised descriptors), so a denominator
    # multiplied by the visibility test gives it (x / (d * 1) = x / d exactly, x / 0 = inf),
    # at a third of ``where``'s cost on CPU and one pass fewer than dividing by it afterwards.
    # (The test is written into a float tensor: a comparison into bool, and arithmetic with
    # a bool operand, run several times slower on CPU than the same into and with floats.)
    visible = torch.ge(count, 0.5, out=torch.empty_like(count))
    denominator = torch.add(count, 1e-3).mul_(visible)
    return torch.sub(count, zncc, out=zncc).add_(1e-3).div_(denominator).view(samples, -1)


def _lookup(frame_desc: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Bilinear lookups (k, C + 1, S / k, R) of ``frame_desc`` (1, C + 1, H, W) at ``grid``
    (1, S, R, 2): the samples split into ``k`` batches of the same frame, in order.

    Why batches: ATen's CPU ``grid_sample`` spreads its work over threads by batch only, so
    one frame's lookups (batch 1) ran on one core however many torch had. The frame
    expanded to ``k`` batches (a view: no copy) with the samples split between them gives
    each thread its share: 2.2x faster on two threads, the same numbers bit for bit (each
    lookup is computed alone). ``k`` is the largest divisor of S up to the thread count; on
    CUDA, which spreads every lookup over the device anyway, 1.
    """
    samples = grid.shape[1]
    k = 1
    if frame_desc.device.type == 'cpu':
        k = max(d for d in range(1, min(torch.get_num_threads(), samples) + 1) if samples % d == 0)
    batch = frame_desc.expand(k, -1, -1, -1) if k > 1 else frame_desc
    return F.grid_sample(
        batch,
        grid.view(k, samples // k, *grid.shape[2:]),
        mode='bilinear',
        padding_mode='zeros',
        align_corners=True,
    )


def normalised_rows(rays: EpipolarRays) -> tuple[torch.Tensor, torch.Tensor]:
    """One frame's rays as the search takes them: ``a`` (3, R) and ``b`` (3,) rescaled to
    ``grid_sample``'s [-1, 1] (``EpipolarRays._normalised``), rows along the contiguous axis."""
    a, b = rays._normalised()
    return a[0].T.contiguous(), b[0]


def _search_rows(
    key_desc: torch.Tensor,
    frame_desc: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    samples: int,
    refine: int,
    with_distinctiveness: bool,
    reject_edges: bool,
) -> SearchResult:
    k = torch.arange(samples, device=lo.device, dtype=lo.dtype)
    step = (hi - lo) / (samples - 1)
    grid = torch.addcmul(lo[None, :], step[None, :], k[:, None])  # (S, R)
    cost = _frame_cost(key_desc, frame_desc, a, b, grid)
    c1, best = _min0(cost)
    distinct = _distinctiveness(cost, best, c1) if with_distinctiveness else c1
    if refine == 0:  # the samples are already about a pixel apart: the parabola goes through them
        j = best.clamp(1, samples - 2)
        found = _parabola(grid, j, step, *_three(cost, j), c1, distinct)
    else:
        found = _refined(key_desc, frame_desc, a, b, grid, step, best, c1, distinct, refine)
    if reject_edges:  # the best sample at an end: the minimum lies outside the interval
        found.ok &= (best > 0) & (best < samples - 1)
    return found


def _refined(
    key_desc: torch.Tensor,
    frame_desc: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    grid: torch.Tensor,
    step: torch.Tensor,
    best: torch.Tensor,
    c1: torch.Tensor,
    distinct: torch.Tensor,
    refine: int,
) -> SearchResult:
    """``refine`` finer samples each side of the best coarse one, then the parabola through them."""
    fine_step = step / refine
    offsets = torch.arange(-refine, refine + 1, device=grid.device, dtype=grid.dtype)
    fine = torch.addcmul(_gather(grid, best)[None, :], fine_step[None, :], offsets[:, None])
    # The middle fine sample is the best coarse one (offset 0: the same rho, the same cost
    # c1): only the others are looked up.
    sides = _frame_cost(key_desc, frame_desc, a, b, torch.cat((fine[:refine], fine[refine + 1 :])))
    fcost = torch.cat((sides[:refine], c1[None, :], sides[refine:]))
    j = _min0(fcost)[1].clamp(1, 2 * refine - 1)
    return _parabola(fine, j, fine_step, *_three(fcost, j), c1, distinct)


def _min0(cost: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``cost.min(dim=0)`` of a samples-first (S, R) tensor (values and first indices).

    Why not ``min(dim=0)``: on CPU its indices make it some 20x slower than ``amin`` over
    short columns. The first index of the minimum is the largest of ``S - s`` over the
    samples equal to it, so an ``amin``, a comparison (into floats: into bool it is several
    times slower) and an ``amax`` give the same values and indices at a fraction of the cost.
    """
    samples = cost.shape[0]
    c1 = cost.amin(dim=0)
    hit = torch.eq(cost, c1, out=torch.empty_like(cost))
    first = samples - hit.mul_(_weights(samples, cost.dtype, cost.device)).amax(dim=0).long()
    if int(first.max()) == samples:  # a NaN minimum equals nothing: min's own semantics (degenerate rays)
        return cost.min(dim=0)
    return c1, first


@functools.lru_cache(maxsize=32)
def _weights(samples: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``S, S - 1, ..., 1`` as an (S, 1) column, built once per sample count (:func:`_min0`)."""
    return torch.arange(samples, 0, -1, dtype=dtype, device=device)[:, None]


def _gather(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``t[idx[r], r]`` of a samples-first (S, R) tensor."""
    return torch.gather(t, 0, idx[None, :])[0]


def _three(cost: torch.Tensor, j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``cost[j - 1, r]``, ``cost[j, r]``, ``cost[j + 1, r]`` of a samples-first (S, R) tensor, one gather."""
    near = j[None, :] + torch.arange(-1, 2, device=j.device)[:, None]
    return torch.gather(cost, 0, near).unbind(0)


def _parabola(
    grid: torch.Tensor,
    j: torch.Tensor,
    step: torch.Tensor,
    cm: torch.Tensor,
    c0: torch.Tensor,
    cp: torch.Tensor,
    c1: torch.Tensor,
    distinct: torch.Tensor,
) -> SearchResult:
    """Sub-sample minimum of the parabola through samples ``j - 1, j, j + 1`` of ``grid`` (S, R).

    Written with the fewest whole-row passes that give the same numbers as the plain form
    (``cm - 2 c0 + cp``, ``0.5 slope / curvature``, ``c0 - 0.25 slope delta``): the factors
    2, 0.5 and 0.25 are powers of two, so folding them into ``alpha`` or into the halved slope
    rounds nothing differently. It runs once per search bucket; on CPU each pass over a
    bucket's rows costs about as much in dispatch as in arithmetic.
    """
    curvature = torch.sub(cm, c0, alpha=2.0).add_(cp)
    # finite and > 0 (NaN fails both comparisons, -inf the first): one test fewer than isfinite
    ok = (curvature > 0) & (curvature < math.inf) & torch.isfinite(c1)
    half_slope = torch.sub(cm, cp).mul_(0.5)
    delta = torch.div(half_slope, torch.where(ok, curvature, 1.0)).clamp_(-1.0, 1.0)
    rho = _gather(grid, j).add_(delta * step)
    best_cost = torch.where(ok, torch.sub(c0, half_slope.mul_(delta), alpha=0.5), math.inf)
    return SearchResult(rho, best_cost, distinct, ok)


def search_interval(
    key_desc: torch.Tensor,
    frame_desc: torch.Tensor,
    rays: EpipolarRays | tuple[torch.Tensor, torch.Tensor],
    lo: torch.Tensor,
    hi: torch.Tensor,
    samples: int,
    refine: int,
    chunk_elements: int = 1 << 22,
    with_distinctiveness: bool = True,
    reject_edges: bool = False,
) -> SearchResult:
    """Best inverse depth of each pixel in ``[lo, hi]`` (M,) against one frame.

    ``key_desc`` (C, M) keyframe descriptors, ``frame_desc`` (1, C + 1, H, W) the frame's
    descriptors with their visibility channel, ``rays`` the pixels' epipolar rays into it
    (or :func:`normalised_rows` of them, which a caller searching several buckets of one frame
    computes once).
    ``refine`` fine samples on each side of the best coarse one (0: the parabola goes through
    the coarse samples themselves). Memory is bounded by ``chunk_elements`` as in the sweep.
    ``with_distinctiveness=False`` skips the second-best ratio (``distinct`` is then undefined):
    a short search around a converged estimate does not use it. ``reject_edges``: a best
    coarse sample at either end of the interval is not ``ok`` (the minimum lies outside it).
    """
    m = int(lo.numel())
    if m == 0:
        empty = lo.new_zeros(0)
        return SearchResult(empty, empty, empty, torch.zeros(0, dtype=torch.bool, device=lo.device))
    a, b = normalised_rows(rays) if isinstance(rays, EpipolarRays) else rays
    # On a CPU, the whole search of each row in one native pass (the same numbers).
    found = native_frame_search(
        key_desc, frame_desc, a, b, lo, hi, samples, refine, with_distinctiveness, reject_edges
    )
    if found is not None:
        return SearchResult(*found)
    chunk = rows_per_chunk(1, key_desc.shape[0] + 1, samples, chunk_elements)
    parts = [
        _search_rows(
            key_desc[:, s : s + chunk],
            frame_desc,
            a[:, s : s + chunk],
            b,
            lo[s : s + chunk],
            hi[s : s + chunk],
            samples,
            refine,
            with_distinctiveness,
            reject_edges,
        )
        for s in range(0, m, chunk)
    ]
    if len(parts) == 1:
        return parts[0]
    return SearchResult(
        *(torch.cat([getattr(p, f) for p in parts]) for f in ('rho', 'cost', 'distinct', 'ok'))
    )
