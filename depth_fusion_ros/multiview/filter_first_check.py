"""A pixel's first measurement, checked once more at one sample a pixel: none from a repeat.

Step 2 of ``filter.py``'s flow, between the searches and the update (``filter_frame_update``).
Why: a pixel without an estimate is searched over the whole inverse-depth range in
``filter.long_samples`` samples, tens of pixels apart along its epipolar line, and a hole's
filled prior (``filter_new_keyframe.fill_holes``) is its neighbours' mean; either way the
first match is taken from few samples, and every later search of the estimate is a short one
around it (+- ``min_search_px``, about a pixel). On a texture that repeats itself along the
line every few pixels (stripes, a grille, blinds, a keyboard) the first match is a
neighbouring period about as often as the right one, and the repeat then fills every later
short search with a match: the wrong estimate is confirmed frame after frame and carried into
the next keyframes. A striped far wall gave a quarter to a third of a stream's estimates at
about half their depth, consistent with one another, and the fusion 1.01-1.05x its input
(docs/multi_view.md, "A repeat along the line").

Here every first measurement (an estimate with no measurement yet: a birth, a filled hole, an
estimate carried across a jump) is searched again over +- ``first_check_px`` pixels around its
match at one sample a pixel, and counts only where no other minimum there comes within
``first_check_distinctiveness`` of the best (``1 - c1 / c2``, the whole-range search's own
test, ``min_distinctiveness``, which its coarse samples cannot apply to a repeat a few pixels
long). Where it counts, the window's best is the measurement: the coarse search's match may
lie beside it, or on a weaker repeat. A birth that fails is not born (the pixel is searched
again in a later frame, where the line may cross the texture differently); a prior that fails
takes an outlier vote, as a match that failed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from ..true_indices import true_indices
from .filter_geometry import FrameGeometry, grid_rows_in_place, row_motion
from .filter_keyframe import FilterKeyframe

if TYPE_CHECKING:
    from .filter import DepthFilter


def check_first_matches(
    filt: DepthFilter,
    key: FilterKeyframe,
    rows: torch.Tensor,
    desc: torch.Tensor,
    a_r: torch.Tensor,
    geo: FrameGeometry,
    x: torch.Tensor,
    j_x: torch.Tensor,
    cost: torch.Tensor,
    valid: torch.Tensor,
) -> torch.Tensor:
    """``valid`` (per searched row, changed in place) less the first measurements whose match
    is not distinct within ``first_check_px`` pixels (see module); where it is, the match ``x``
    becomes the best of that window, ``j_x`` the motion there and ``cost`` its cost (all three
    changed in place: the measurement and what is recorded of it agree).

    ``rows``: the searched keyframe rows; ``desc``: the frame's descriptors; ``a_r``: the rows'
    projections at infinity (3, R) in the frame ``geo`` describes; ``x``, ``j_x``: each
    search's match and the epipolar motion there (px per unit inverse depth).
    """
    c = filt.config
    if c.first_check_px <= 0:
        return valid
    first = true_indices(valid & (key.updates.index_select(0, rows) == 0))
    if first.numel() == 0:
        return valid
    cam = filt.camera
    a, b = grid_rows_in_place(a_r.index_select(1, first), geo.b, cam.width, cam.height)
    match = x.index_select(0, first)
    half = c.first_check_px / torch.clamp(j_x.index_select(0, first), min=1e-6)
    found = filt.search(
        key.key_desc.index_select(1, rows.index_select(0, first)),
        desc,
        (a, b),
        match - half,
        match + half,
        2 * round(c.first_check_px) + 1,  # one sample a pixel
        0,
        filt._chunk_elements,
        with_distinctiveness=True,
    )
    # The whole window is searched, also where it reaches past the inverse-depth range (clamped,
    # it would see less of a repeat); its best is a measurement only inside the range.
    rho_min, rho_max = filt.rho_range
    distinct = found.ok & (found.distinct >= c.first_check_distinctiveness)
    distinct &= (found.rho >= rho_min) & (found.rho <= rho_max)
    # The window's best, not the first match: a coarse search that landed beside the minimum
    # (or on a weaker repeat within the window) is put right by the samples a pixel apart.
    x.index_copy_(0, first, torch.where(distinct, found.rho, match))
    cost.index_copy_(0, first, torch.where(distinct, found.cost, cost.index_select(0, first)))
    j_x.index_copy_(0, first, row_motion(a_r.index_select(1, first), geo.b, x.index_select(0, first)))
    return valid.index_copy_(0, first, distinct)
