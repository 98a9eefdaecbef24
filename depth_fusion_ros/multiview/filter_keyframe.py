"""The temporal filter's keyframe: its image descriptors, candidate pixels and their posterior.

One object per filter keyframe (``filter.DepthFilter.key``); propagation makes the next one
(``filter_new_keyframe.propagate``). Plain tensors, so the state moves to any device with
the filter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from .filter_update import BetaGaussian

if TYPE_CHECKING:
    from .filter import DepthFilter


def no_estimate(filt: DepthFilter) -> tuple[float, float, float, float, int, bool]:
    """Mean, variance, Beta ``a``, ``b``, measurement count and prior flag of a pixel without an
    estimate: the middle of the inverse-depth range, its whole span as the variance, the prior
    Beta. A new keyframe's pixels start so (``filter_new_keyframe.fresh_state``) and an estimate
    that failed too often goes back to it (``filter_matches``)."""
    lo, hi = filt.rho_range
    return 0.5 * (lo + hi), (hi - lo) ** 2, filt.config.init_a, filt.config.init_b, 0, False


@dataclass
class FilterKeyframe:
    """The filter's keyframe: image descriptors, candidate pixels and their posterior."""

    pose: np.ndarray  # T_wk
    desc: torch.Tensor  # (1, C + 1, H, W) descriptors of the whole image (the next keyframe's observation)
    flat: torch.Tensor  # (M,) long pixel index v * W + u
    us: torch.Tensor
    vs: torch.Tensor
    key_desc: torch.Tensor  # (C, M)
    grad: torch.Tensor  # (2, M) grey gradient (gx, gy) per px after the matching blur
    state: BetaGaussian
    updates: torch.Tensor  # (M,) measurements fused (0 = no estimate yet)
    prior: torch.Tensor  # (M,) bool: mu, var hold a prior (measured, carried or filled): short searches
    cost: torch.Tensor  # (M,) last matching cost
    attempts: torch.Tensor  # (M,) long searches spent on a pixel without an estimate
    #: The stream's first keyframe (or the first after a restart): nothing was carried into it,
    #: so every estimate was born here (``filter.first_keyframe_min_updates``).
    first: bool = False
    # (padded image,) long: the row at each pixel of the image padded by seed_radius, M where
    # none (built on first use: the seed bracket's neighbour lookups)
    padded_rows: torch.Tensor | None = None
    padded_flat: torch.Tensor | None = None  # (M,) long: each row's index in that padded image
    #: Camera-to-world poses of the last frames that updated this keyframe or, carried, the
    #: keyframes before it, in order (``multiview/focal_bias.py``)
    update_poses: list[np.ndarray] = field(default_factory=list)


def padded_maps(filt: DepthFilter, key: FilterKeyframe) -> tuple[torch.Tensor, torch.Tensor]:
    """Each keyframe row's pixel in the image padded by ``seed_radius`` on every side, and that
    padded image's row at each pixel (the row count where there is no candidate): a window of
    a row is then a fixed set of offsets, never outside the map (the seed bracket's neighbour
    lookups, ``filter_bracket``). Made once per keyframe."""
    if key.padded_rows is None or key.padded_flat is None:
        r = filt.config.seed_radius
        h, w = filt.camera.height, filt.camera.width
        wp, m = w + 2 * r, int(key.flat.numel())
        key.padded_flat = (key.vs.long() + r) * wp + key.us.long() + r
        key.padded_rows = torch.full(((h + 2 * r) * wp,), m, dtype=torch.long, device=filt.device)
        key.padded_rows.index_copy_(0, key.padded_flat, torch.arange(m, device=filt.device))
    return key.padded_flat, key.padded_rows
