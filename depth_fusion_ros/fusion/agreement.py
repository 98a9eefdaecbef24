"""Per-pixel agreement of the fused points around a pixel: the second factor of the confidence.

The support confidence ``exp(-D_p / σ1)`` (:func:`.interpolation.confidence_from_support`)
says how near a pixel's points are, not whether they agree. Measured on every sequence this
project holds (docs/fusion.md, "Confidence"), its highest tenth was *less* accurate than its
middle: the pixels on and next to the points of Ω inherit each point's own error there,
where farther pixels average many points. Where the offsets ``v = m - s`` of the nearby points
scatter, the fused depth follows whichever point is nearest and is wrong by about that
scatter; where they agree, it is right. So the confidence is multiplied by
``exp(-spread_p / (τ · depth_p))``, ``spread_p`` the standard deviation of the nearby offsets
(a Gaussian window of ``sigma`` pixels, normalised over the points in it: one normalised
convolution, OpenCV, ~3 ms at 320x240). A pixel with no point within the window keeps its
support confidence (factor 1; that confidence is already small there).
"""

from __future__ import annotations

import cv2
import numpy as np

#: Window sums at or below this hold no point (OpenCV's kernel is cut at about 4 sigma, so
#: beyond every point's reach the sum is exactly 0).
_EMPTY = 1e-12


def offset_spread(offsets: np.ndarray, points: np.ndarray, sigma: float) -> np.ndarray:
    """Standard deviation of ``offsets`` at ``points`` (bool mask) in a Gaussian window of
    ``sigma`` pixels around every pixel; 0 where the window holds no point."""
    w = (points & np.isfinite(offsets)).astype(np.float32)
    if not w.any():
        return np.zeros(offsets.shape, dtype=np.float32)
    # Centred on the points' median: E[v²] - E[v]² cancels otherwise (0.3 m offsets that all
    # agree gave a 0.2 mm "spread" in float32). float32 after centring: 3.2 ms a 320x240
    # keyframe against 7.0 ms in float64, the spread the same to 1e-7 m.
    v = np.where(w > 0, offsets - np.median(offsets[w > 0]), 0.0).astype(np.float32)

    def blur(x: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(x, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_CONSTANT)

    total = blur(w)
    empty = total <= _EMPTY
    safe = np.where(empty, 1.0, total)
    mean = blur(w * v) / safe
    variance = blur(w * v * v) / safe - mean * mean
    spread = np.sqrt(np.maximum(variance, 0.0))
    spread[empty] = 0.0
    return spread.astype(np.float32)


def agreement(
    depth: np.ndarray, base: np.ndarray, m: np.ndarray, points: np.ndarray, sigma: float, tau: float
) -> np.ndarray:
    """``exp(-spread / (tau · depth))`` per pixel, in (0, 1]: the offsets ``m - base`` at
    ``points`` (Ω), their local spread relative to the fused ``depth``. ``tau`` 0: all 1."""
    if tau <= 0:
        return np.ones(depth.shape, dtype=np.float32)
    with np.errstate(invalid='ignore'):
        spread = offset_spread(m - base, points, sigma)
        factor = np.exp(-spread / (tau * np.maximum(depth, 1e-3)))
    return np.nan_to_num(factor, nan=0.0).astype(np.float32)
