"""Short epipolar search of keyframe pixels in one new frame, each within its own interval.

The sweep (``semidense.py``) searches every pixel over the whole inverse-depth range in
``n`` neighbours at once. The filter knows, per pixel, where the answer should be (its prior
mean +- a few standard deviations), so one frame is searched over a short interval: a few
samples per pixel instead of tens, and one frame instead of four. That is what makes an
update per posed frame affordable. The cost is the sweep's (``cost_volume.sample_cost``:
``1 - ZNCC`` of the same patch descriptors) on a per-pixel grid of inverse depths
``lo + (hi - lo) t``, then a finer grid around the best sample and a parabola, as the sweep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .cost_volume import EpipolarRays, rows_per_chunk


@dataclass
class SearchResult:
    """Per pixel: refined inverse depth, its cost, the second-best ratio and whether it is usable."""

    rho: torch.Tensor
    cost: torch.Tensor
    distinct: torch.Tensor
    ok: torch.Tensor


def _gather(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return torch.gather(t, 1, idx[:, None])[:, 0]


def _distinctiveness(cost: torch.Tensor, best: torch.Tensor, c1: torch.Tensor) -> torch.Tensor:
    """Modified second-best ratio ``1 - c1 / c2`` over local minima more than one sample away."""
    inf = torch.full_like(cost[:, :1], math.inf)
    left = torch.cat((inf, cost[:, :-1]), dim=1)
    right = torch.cat((cost[:, 1:], inf), dim=1)
    is_min = (cost <= left) & (cost <= right) & torch.isfinite(cost)
    idx = torch.arange(cost.shape[1], device=cost.device)
    far = (idx[None, :] - best[:, None]).abs() > 1
    c2 = torch.where(is_min & far, cost, torch.full_like(cost, math.inf)).min(dim=1).values
    largest = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, -math.inf)).max(dim=1).values
    c2 = torch.where(torch.isfinite(c2), c2, largest)
    return torch.clamp(1.0 - c1 / torch.clamp(c2, min=1e-6), 0.0, 1.0)


def frame_cost(
    key_desc: torch.Tensor, frame_desc: torch.Tensor, rays: EpipolarRays, rho: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``1 - ZNCC`` (M, S) against one frame and whether the frame sees each sample (soft, 0-1).

    ``cost_volume.sample_cost`` for a single neighbour (same numbers), without the sum over
    neighbours: one ``grid_sample`` and one contraction over the descriptor channels.
    """
    channels = key_desc.shape[0]
    grid = rays.grid(rho)
    sampled = F.grid_sample(frame_desc, grid, mode='bilinear', padding_mode='zeros', align_corners=True)[0]
    count = sampled[channels]
    zncc = sampled[0] * key_desc[0, :, None]
    for c in range(1, channels):
        zncc.addcmul_(sampled[c], key_desc[c, :, None])
    return (count - zncc + 1e-3) / (count + 1e-3), count


def _search_rows(
    key_desc: torch.Tensor,
    frame_desc: torch.Tensor,
    rays: EpipolarRays,
    lo: torch.Tensor,
    hi: torch.Tensor,
    samples: int,
    refine: int,
    with_distinctiveness: bool,
) -> SearchResult:
    t = torch.linspace(0.0, 1.0, samples, device=lo.device, dtype=lo.dtype)
    step = (hi - lo) / (samples - 1)
    grid = lo[:, None] + step[:, None] * (t[None, :] * (samples - 1))
    cost, count = frame_cost(key_desc, frame_desc, rays, grid)
    cost = torch.where(count >= 0.5, cost, torch.full_like(cost, math.inf))
    c1, best = cost.min(dim=1)
    distinct = _distinctiveness(cost, best, c1) if with_distinctiveness else c1
    if refine == 0:  # a short search: its samples are already about a pixel apart
        j = best.clamp(1, samples - 2)
        cm, c0, cp = _gather(cost, j - 1), _gather(cost, j), _gather(cost, j + 1)
        return _parabola(grid, j, step, cm, c0, cp, c1, distinct)
    fine_step = step / refine
    offsets = torch.arange(-refine, refine + 1, device=lo.device, dtype=lo.dtype)
    fine = _gather(grid, best)[:, None] + offsets[None, :] * fine_step[:, None]
    fcost, fcount = frame_cost(key_desc, frame_desc, rays, fine)
    fcost = torch.where(fcount >= 0.5, fcost, torch.full_like(fcost, math.inf))
    j = fcost.argmin(dim=1).clamp(1, 2 * refine - 1)
    cm, c0, cp = _gather(fcost, j - 1), _gather(fcost, j), _gather(fcost, j + 1)
    return _parabola(fine, j, fine_step, cm, c0, cp, c1, distinct)


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
    """Sub-sample minimum of the parabola through samples ``j - 1, j, j + 1`` of ``grid``."""
    curvature = cm - 2.0 * c0 + cp
    ok = torch.isfinite(curvature) & (curvature > 0) & torch.isfinite(c1)
    safe = torch.where(ok, curvature, torch.ones_like(curvature))
    delta = torch.clamp(0.5 * (cm - cp) / safe, -1.0, 1.0)
    rho = _gather(grid, j) + delta * step
    best_cost = torch.where(ok, c0 - 0.25 * (cm - cp) * delta, torch.full_like(c0, math.inf))
    return SearchResult(rho, best_cost, distinct, ok)


def search_interval(
    key_desc: torch.Tensor,
    frame_desc: torch.Tensor,
    rays: EpipolarRays,
    lo: torch.Tensor,
    hi: torch.Tensor,
    samples: int,
    refine: int,
    chunk_elements: int = 1 << 22,
    with_distinctiveness: bool = True,
) -> SearchResult:
    """Best inverse depth of each pixel in ``[lo, hi]`` (M,) against one frame.

    ``key_desc`` (C, M) keyframe descriptors, ``frame_desc`` (1, C + 1, H, W) the frame's
    descriptors with their visibility channel, ``rays`` the pixels' epipolar rays into it.
    ``refine`` fine samples on each side of the best coarse one (0: the parabola goes through
    the coarse samples themselves). Memory is bounded by ``chunk_elements`` as in the sweep.
    ``with_distinctiveness=False`` skips the second-best ratio (``distinct`` is then undefined):
    a short search around a converged estimate does not use it.
    """
    m = int(lo.numel())
    if m == 0:
        empty = lo.new_zeros(0)
        return SearchResult(empty, empty, empty, torch.zeros(0, dtype=torch.bool, device=lo.device))
    chunk = rows_per_chunk(1, key_desc.shape[0] + 1, samples, chunk_elements)
    parts = [
        _search_rows(
            key_desc[:, s : s + chunk],
            frame_desc,
            rays.chunk(s, s + chunk),
            lo[s : s + chunk],
            hi[s : s + chunk],
            samples,
            refine,
            with_distinctiveness,
        )
        for s in range(0, m, chunk)
    ]
    if len(parts) == 1:
        return parts[0]
    return SearchResult(
        *(torch.cat([getattr(p, f) for p in parts]) for f in ('rho', 'cost', 'distinct', 'ok'))
    )
