"""A new filter keyframe: its candidate pixels, and the estimates carried into it.

Step 3 of ``filter.py``'s flow (and the stream's first frame). :func:`new_keyframe` makes
a keyframe without estimates from a frame; :func:`propagate` makes one from the old
keyframe (LSD-SLAM): the estimates are warped into it (``filter_propagate``), holes
between carried estimates get their neighbours' mean as a prior (:func:`fill_holes`), and
every pixel left without a prior gets its first measurement from the previous keyframe
image (``filter_frame_update``).
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..geometry import relative_pose, rotation_angle
from ..true_indices import true_indices
from .descriptors import gaussian_blur
from .filter_frame_update import update_frame
from .filter_keyframe import FilterKeyframe, no_estimate
from .filter_propagate import warp_estimates
from .filter_update import BetaGaussian
from .filter_window import box_sum
from .semidense import candidate_mask

if TYPE_CHECKING:
    from .filter import DepthFilter

log = logging.getLogger(__name__)


def fresh_state(filt: DepthFilter, m: int) -> tuple[BetaGaussian, torch.Tensor, torch.Tensor]:
    """The posterior, measurement count and cost of ``m`` pixels without an estimate
    (``filter_keyframe.no_estimate``)."""
    mu, var, a, b, _, _ = no_estimate(filt)
    full = lambda value: torch.full((m,), float(value), device=filt.device)  # noqa: E731
    state = BetaGaussian(full(mu), full(var), full(a), full(b))
    return state, torch.zeros(m, dtype=torch.long, device=filt.device), full(math.nan)


def new_keyframe(
    filt: DepthFilter, image: torch.Tensor, desc: torch.Tensor, T_wk: np.ndarray
) -> FilterKeyframe:
    """A keyframe at this frame (``desc``: its descriptors) with no estimates yet."""
    # One blur for the candidate test and the gradients (candidate_mask's own smoothing).
    smooth = gaussian_blur(image[None], filt.matching.blur_sigma)[0]
    cand = candidate_mask(image, filt._candidates, smooth=smooth)
    vs, us = torch.nonzero(cand, as_tuple=True)
    width = filt.camera.width
    flat = vs * width + us
    # Candidates lie away from the border, so the central differences stay inside. Flat
    # index_select gathers: the same values as 2-D advanced indexing, several times cheaper.
    pixels = smooth.reshape(-1)
    at = lambda offset: pixels.index_select(0, flat + offset)  # noqa: E731
    grad = torch.stack(((at(1) - at(-1)) * 0.5, (at(width) - at(-width)) * 0.5))
    channels = desc.shape[1] - 1
    if desc.stride(1) == 1:  # CPU (DepthFilter._describe): a pixel's channels adjoin
        key_desc = desc[0].permute(1, 2, 0).reshape(-1, channels + 1).index_select(0, flat)
        key_desc = key_desc[:, :channels].T.contiguous()
    else:
        key_desc = desc[0, :channels].reshape(channels, -1).index_select(1, flat)
    state, updates, cost = fresh_state(filt, int(flat.numel()))
    return FilterKeyframe(
        T_wk,
        desc,
        flat,
        us.float(),
        vs.float(),
        key_desc,
        grad,
        state,
        updates,
        torch.zeros_like(updates, dtype=torch.bool),
        cost,
        torch.zeros_like(updates),
    )


def propagate(
    filt: DepthFilter, old: FilterKeyframe, image: torch.Tensor, desc: torch.Tensor, T_wn: np.ndarray
) -> FilterKeyframe:
    """New keyframe at this frame: carried estimates where they land, first measurements elsewhere."""
    left = filt.clock.switch('propagation')
    new = new_keyframe(filt, image, desc, T_wn)
    c = filt.config
    rows = true_indices(old.updates > 0)
    new.first = old.first and rows.numel() == 0  # nothing to carry: still the stream's first
    T_nk = relative_pose(old.pose, T_wn)
    # A jump (a relocalisation, a gap in the stream): turned further than the filter matches
    # across. The estimates are carried by geometry alone, and those hidden in the new view
    # (behind a surface the old keyframe did not see) land on it all the same; across a
    # jump that is a large share of them. So they come as priors to confirm (their count
    # restarts: published once new views measured them), and no first measurement is taken
    # from the old keyframe image (too turned for its patches to match).
    turn = math.degrees(rotation_angle(T_nk[:3, :3]))
    jump = turn > c.max_rotation_deg
    if jump:
        filt.stats.jumps += 1
        log.debug('filter keyframe across a %.0f deg jump: %d estimates to confirm', turn, int(rows.numel()))
    warped = warp_estimates(
        old.us[rows],
        old.vs[rows],
        old.state.mu[rows],
        filt.camera.K,
        T_nk,
        filt.camera.size,
        filt.rho_range,
    )
    position = torch.full((filt.camera.width * filt.camera.height,), -1, dtype=torch.long, device=filt.device)
    position.index_copy_(0, new.flat, torch.arange(new.flat.numel(), device=filt.device))
    # Reads by index_select (the same values as advanced indexing, several times cheaper on
    # CPU); the writes stay index_put_, as before (a tie in the z-buffer can repeat a target).
    at = position.index_select(0, warped.target)
    landed = true_indices(at >= 0)
    sources = rows.index_select(0, warped.source)
    kept = lambda t: t.index_select(0, landed)  # noqa: E731
    at, src, rho, scale4 = kept(at), kept(sources), kept(warped.rho), kept(warped.scale) ** 4
    old_at = lambda t: t.index_select(0, src)  # noqa: E731
    st = new.state
    st.mu[at] = rho
    inflated = old_at(old.state.var) * scale4 * c.propagation_inflation
    st.var[at] = inflated + (c.propagation_relative_sigma * rho) ** 2
    st.a[at] = old_at(old.state.a)
    st.b[at] = old_at(old.state.b)
    new.updates[at] = 0 if jump else old_at(old.updates)
    new.prior[at] = True
    new.cost[at] = old_at(old.cost)
    # Only estimates with fill_min_updates measurements fill holes: a young one may be wrong,
    # and a prior filled from it is confirmed by the short searches around it.
    mature = true_indices(old.updates.index_select(0, sources) >= c.fill_min_updates)
    variance = old.state.var.index_select(0, sources) * warped.scale**4
    filled = fill_holes(
        filt,
        new,
        warped.target.index_select(0, mature),
        warped.rho.index_select(0, mature),
        variance.index_select(0, mature),
    )
    # Pixels without a prior: a first measurement from the previous keyframe image.
    T_ok = relative_pose(T_wn, old.pose)
    if not jump and float(np.linalg.norm(T_ok[:3, 3])) / filt._scene >= c.min_parallax:
        update_frame(filt, new, old.desc, T_ok, only=new.updates == 0)
    log.debug(
        'filter keyframe: %d carried of %d, %d filled, %d pixels',
        int(at.numel()),
        int(rows.numel()),
        filled,
        int(new.flat.numel()),
    )
    filt.clock.switch(left)
    return new


def fill_holes(
    filt: DepthFilter, new: FilterKeyframe, target: torch.Tensor, rho: torch.Tensor, var: torch.Tensor
) -> int:
    """A prior for new pixels among carried estimates: the mean of those within ``fill_radius``.

    LSD-SLAM fills the holes that nearest-pixel propagation leaves (rounding, new
    candidates between carried ones) from their neighbours. The prior's variance is the
    neighbours' mean variance plus their spread (large across a depth edge), inflated as
    a propagation; it counts as no measurement (``updates`` stays 0), so the pixel is
    published only after frames confirm it, but it gets a short search instead of a
    whole-range one. Returns the number of pixels filled.
    """
    c = filt.config
    if c.fill_radius <= 0 or target.numel() == 0:
        return 0
    h, w = filt.camera.height, filt.camera.width
    maps = torch.zeros((4, h * w), dtype=rho.dtype, device=rho.device)
    maps[0, target] = 1.0
    maps[1, target] = rho
    maps[2, target] = rho * rho
    maps[3, target] = var
    sums = box_sum(maps.view(4, h, w), c.fill_radius).view(4, h * w).index_select(1, new.flat)
    n = sums[0]
    hole = ~new.prior & (n >= c.fill_min_neighbours)
    n = torch.clamp(n, min=1.0)
    mean = sums[1] / n
    spread = torch.clamp(sums[2] / n - mean * mean, min=0.0)
    fill_var = (sums[3] / n + spread) * c.propagation_inflation + (c.propagation_relative_sigma * mean) ** 2
    st = new.state
    st.mu = torch.where(hole, mean, st.mu)
    st.var = torch.where(hole, fill_var, st.var)
    new.prior = new.prior | hole
    return int(hole.sum())
