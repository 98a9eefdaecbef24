"""The degraded outputs of the guard's ladder (``guard.DECISIONS`` below ``fewer_points``).

``full`` and ``fewer_points`` are the ordinary interpolation (over Ω or the trusted points);
this module makes the three others from the single-view depth the fusion starts from:

* ``scale_only`` — a smooth *multiplicative* correction: the log ratios ``log(m/s)`` of the
  trusted points interpolated with the proximity weight W1 only, at a large scale
  (``scale_sigma_px``). It fixes regional scale (a wall that is 15 % too far) but moves no
  edge and copies no single point's error into the depth;
* ``single_scaled`` — ``s`` times the global multi-view scale (one number);
* ``single_view`` — ``s`` as it is.

The per-pixel confidence is the support confidence of the points used (1 on a point,
``exp(-D/σ)`` with the weighted distance ``D``) times the keyframe confidence of the verdict;
constant for ``single_scaled``, 0 for ``single_view``.
"""

from __future__ import annotations

import numpy as np

from .guard import GuardConfig, GuardVerdict
from .interpolation import confidence_from_support, interpolate
from .selection import MIN_DEPTH
from .weights import WeightParams


def guarded_depth(
    base: np.ndarray, m: np.ndarray, verdict: GuardVerdict, config: object, guard: GuardConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and per-pixel confidence of a degraded decision (``config``: a ``FusionConfig``)."""
    finite = np.isfinite(base)
    confidence = np.zeros(base.shape, dtype=np.float32)
    if verdict.decision == 'scale_only':
        with np.errstate(invalid='ignore', divide='ignore'):
            log_base = np.log(np.maximum(base, MIN_DEPTH)).astype(np.float32)
            log_m = np.log(np.where(m > 0, m, np.nan)).astype(np.float32)
        params = WeightParams(guard.scale_sigma_px, config.sigma2, config.sigma3, 'w1')
        interp = interpolate(
            log_base,
            log_m,
            verdict.trusted,
            params,
            mode='fast',
            fast_stride=config.fast_stride,
            chunk_elements=config.chunk_elements,
            device=config.device,
        )
        offset = np.nan_to_num(interp.offset, nan=0.0)
        depth = base * np.exp(offset)
        confidence = confidence_from_support(interp.support_distance, guard.scale_sigma_px)
        confidence *= np.float32(verdict.confidence)
    elif verdict.decision == 'single_scaled':
        depth = base * np.float32(verdict.scale)
        confidence[finite] = verdict.confidence
    else:
        depth = base.copy()
    with np.errstate(invalid='ignore'):
        depth = np.maximum(depth, MIN_DEPTH).astype(np.float32)
    depth[~finite] = np.nan
    confidence[~np.isfinite(depth)] = 0.0
    return depth, confidence.astype(np.float32)


def limit_reach(
    depth: np.ndarray, base: np.ndarray, support_distance: np.ndarray, reach_px: float
) -> tuple[np.ndarray, float]:
    """Fade the local corrections out with the distance to the points that make them.

    The interpolation's weights are normalised, so a pixel 100 px from every point still
    takes their full offset, though the single-view error there (another region of the
    network's prediction) is unrelated to theirs: extrapolated, a correction adds error.
    Where the points cover little of the image (weak texture) most pixels are such. The
    fused depth is blended towards ``base`` (the single-view depth the fusion started from)
    with weight ``exp(-(D / reach_px)²)``, ``D`` the pixel's weighted distance to its
    points: full corrections near the points, none far from them. Not towards the global
    multi-view scale: the median of the points' ratios is that of the few regions they sit
    in, and on the stress cases it was a worse guess for the rest of the image than
    ``base`` itself (docs/fusion.md).

    Returns the depth and the *coverage*: the mean weight over the finite pixels (the
    share of the correction that was kept).
    """
    with np.errstate(invalid='ignore'):
        d = np.nan_to_num(support_distance, nan=np.inf).astype(np.float32)
        near = np.exp(-np.square(d / np.float32(reach_px))).astype(np.float32)
    out = near * depth + (1.0 - near) * base
    finite = np.isfinite(depth)
    coverage = float(near[finite].mean()) if finite.any() else 0.0
    return np.where(finite, np.maximum(out, MIN_DEPTH), np.nan).astype(np.float32), coverage
