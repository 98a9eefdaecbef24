"""Per-pixel agreement of the fused points around a pixel: the second factor of the confidence.

The support confidence ``exp(-D_p / σ1)`` (:func:`.interpolation.confidence_from_support`)
says how near a pixel's points are, not whether they agree. Measured on every sequence this
project holds (docs/fusion.md, "Confidence"), its highest tenth was *less* accurate than its
middle: the pixels on and next to the points of Ω inherit each point's own error there,
where farther pixels average many points. Where the offsets ``v = m - s`` of the nearby points
scatter, the fused depth follows whichever point is nearest and is wrong by about that
scatter; where they agree, it is right. So the confidence is multiplied by
``exp(-spread_p / (τ · depth_p))``, ``spread_p`` the standard deviation of the nearby offsets
(a Gaussian window of ``sigma`` pixels, normalised over the points in it: one batched
normalised convolution, ``gaussian.py``, shared with stage 3). A pixel with no point within
the window keeps its support confidence (factor 1; that confidence is already small there).
"""

from __future__ import annotations

import numpy as np
import torch

from .gaussian import gaussian_kernel, gaussian_sum

#: Window sums at or below this hold no point (the kernel is cut at 3 sigma, so beyond every
#: point's reach the sum is exactly 0).
_EMPTY = 1e-12


def offset_spread(offsets: np.ndarray, points: np.ndarray, sigma: float, device: str = 'cpu') -> np.ndarray:
    """Standard deviation of ``offsets`` at ``points`` (bool mask) in a Gaussian window of
    ``sigma`` pixels around every pixel; 0 where the window holds no point."""
    at_points = points & np.isfinite(offsets)
    if not at_points.any():
        return np.zeros(offsets.shape, dtype=np.float32)
    # Centred on the points' median: E[v²] - E[v]² cancels otherwise (0.3 m offsets that all
    # agree gave a 0.2 mm "spread" in float32 without it). v is 0 off the points, so the
    # window sums of w·v and w·v² are those of v and v².
    v = np.where(at_points, offsets - np.median(offsets[at_points]), 0.0).astype(np.float32)
    dev = torch.device(device)
    w, v_t = torch.from_numpy(at_points.astype(np.float32)).to(dev), torch.from_numpy(v).to(dev)
    g, _ = gaussian_kernel(sigma, dev)
    total, first, second = gaussian_sum(torch.stack((w, v_t, v_t * v_t)), g)
    empty = total <= _EMPTY
    safe = torch.where(empty, 1.0, total)
    mean = first / safe
    spread = (second / safe - mean * mean).clamp_(min=0.0).sqrt_()
    spread[empty] = 0.0
    return spread.cpu().numpy()


def agreement(
    depth: np.ndarray,
    base: np.ndarray,
    m: np.ndarray,
    points: np.ndarray,
    sigma: float,
    tau: float,
    device: str = 'cpu',
) -> np.ndarray:
    """``exp(-spread / (tau · depth))`` per pixel, in (0, 1]: the offsets ``m - base`` at
    ``points`` (Ω), their local spread relative to the fused ``depth``. ``tau`` 0: all 1."""
    if tau <= 0:
        return np.ones(depth.shape, dtype=np.float32)
    with np.errstate(invalid='ignore'):
        spread = offset_spread(m - base, points, sigma, device)
        factor = np.exp(-spread / (tau * np.maximum(depth, 1e-3)))
    return np.nan_to_num(factor, nan=0.0).astype(np.float32)
