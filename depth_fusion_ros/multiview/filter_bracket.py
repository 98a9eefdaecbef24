"""The seed bracket: a new pixel's first search spans its measured neighbours' range.

A pixel without an estimate next to measured ones (within ``filter.seed_radius`` px) most
likely lies on their surface, so its first search is a few samples over their inverse
depths instead of a whole-range search (the bench's costliest rows). The neighbours' lowest
and highest inverse depth come from a window gather for a few rows, or from a min and a max
filter over the whole image for many (a new keyframe's seeds); both give the same numbers.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .filter_geometry import row_motion
from .filter_keyframe import FilterKeyframe, padded_maps
from .filter_window import window_reduce
from .native_bracket import native_bracket

if TYPE_CHECKING:
    from .filter import DepthFilter


def bracket_seeds(
    filt: DepthFilter,
    key: FilterKeyframe,
    rows: torch.Tensor,
    seeds: torch.Tensor,
    fresh: torch.Tensor,
    a_r: torch.Tensor,
    b: tuple[float, float, float],
    lo: torch.Tensor,
    hi: torch.Tensor,
) -> torch.Tensor | None:
    """First attempt of a pixel without an estimate: its neighbours' range, not the whole range.

    A new pixel next to measured ones (within ``seed_radius`` px) most likely lies on
    their surface: its first search spans the neighbours' inverse depths, widened by
    ``2 min_search_px`` px each side, a few samples instead of a whole-range search
    (its second attempt, if this one fails, is a whole-range one). ``lo``, ``hi`` are
    narrowed in place; returns which rows were bracketed (None: none). ``seeds``: the rows
    of ``fresh`` (the first attempts are among them: tested on those few rows only).
    """
    c = filt.config
    if c.seed_radius <= 0 or seeds.numel() == 0:
        return None
    # The same in one native pass on a CPU (native_bracket); elsewhere the torch code below.
    applied, use = native_bracket(filt, key, rows, seeds, a_r, b, lo, hi)
    if applied:
        return use
    # choose_rows (filter_frame_update) counted this attempt
    sel = seeds.masked_select(key.attempts.index_select(0, rows.index_select(0, seeds)) == 1)
    if sel.numel() == 0 or not bool(key.updates.any()):  # updates >= 0: any() is "any > 0"
        return None
    n_lo, n_hi = neighbour_range(filt, key, rows.index_select(0, sel))
    near = torch.isfinite(n_lo)
    sel, n_lo, n_hi = sel[near], n_lo[near], n_hi[near]
    a_s = a_r.index_select(1, sel)
    rho_min, rho_max = filt.rho_range
    pad = 2.0 * c.min_search_px
    lo.index_copy_(
        0,
        sel,
        torch.clamp(n_lo - pad / torch.clamp(row_motion(a_s, b, n_lo), min=1e-9), rho_min, rho_max),
    )
    hi.index_copy_(
        0,
        sel,
        torch.clamp(n_hi + pad / torch.clamp(row_motion(a_s, b, n_hi), min=1e-9), rho_min, rho_max),
    )
    use = torch.zeros_like(fresh)
    use[sel] = True
    return use


def neighbour_range(
    filt: DepthFilter, key: FilterKeyframe, rows: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lowest and highest measured inverse depth within ``seed_radius`` px of each row's
    pixel (``inf``, ``-inf`` where none): the (2r + 1)^2 window of each row, gathered
    through the keyframe's padded pixel-to-row map, so the cost follows the rows asked
    for, not the image."""
    r = filt.config.seed_radius
    h, w = filt.camera.height, filt.camera.width
    if int(rows.numel()) * (2 * r + 1) ** 2 > h * w:
        return neighbour_range_dense(filt, key, rows)
    wp = w + 2 * r
    m = int(key.flat.numel())
    padded_flat, padded_rows = padded_maps(filt, key)
    d = torch.arange(-r, r + 1, device=filt.device)
    offsets = (d[:, None] * wp + d[None, :]).reshape(-1)
    window = (padded_flat.index_select(0, rows)[:, None] + offsets[None, :]).reshape(-1)
    near = padded_rows.index_select(0, window)  # rows, m for "no candidate there"
    # Gathered first, then "no estimate" where there is no candidate (near == m): the
    # window's entries only, not a copy of the keyframe's state with a spare entry.
    inside = near.clamp(max=m - 1)
    mu = key.state.mu.index_select(0, inside)
    has = (key.updates.index_select(0, inside) > 0) & (near < m)
    shape = (int(rows.numel()), int(offsets.numel()))
    lows = torch.where(has, mu, math.inf).view(shape).amin(dim=1)
    highs = torch.where(has, mu, -math.inf).view(shape).amax(dim=1)
    return lows, highs


def neighbour_range_dense(
    filt: DepthFilter, key: FilterKeyframe, rows: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`neighbour_range` through a min and a max filter over the whole image, for many
    rows (a new keyframe's seeds): its windows would gather more entries than the image
    has pixels. Minima and maxima are exact, so the numbers are the same."""
    r = filt.config.seed_radius
    h, w = filt.camera.height, filt.camera.width
    has = key.updates > 0
    ranges = []
    for empty, pick in ((math.inf, torch.minimum), (-math.inf, torch.maximum)):
        image = torch.full((h * w,), empty, dtype=key.state.mu.dtype, device=filt.device)
        image.scatter_(0, key.flat, torch.where(has, key.state.mu, empty))
        padded = F.pad(image.view(1, h, w), (r, r, r, r), value=empty)[0]
        window = window_reduce(padded, r, lambda acc, x, pick=pick: pick(acc, x, out=acc))
        ranges.append(window.view(-1).index_select(0, key.flat.index_select(0, rows)))
    return ranges[0], ranges[1]
