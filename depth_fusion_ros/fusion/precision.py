"""Each multi-view point's own weight in the interpolation: its precision (issue 11).

The paper weighs a point of Ω only by where it lies (W1) and by the structure of the
single-view depth around it (W2..W4): a point measured once at small parallax bends the
depth as much as one confirmed by twenty frames. The filter knows the difference (its
posterior std), so the interpolation multiplies every weight of point ``q`` by

    c_q = h² / (h² + r_q²),    r_q = depth_std_q / depth_q   (relative std),

with ``h = fusion.std_half_weight``: a point whose relative std is ``h`` counts half, one
with ``r ≪ h`` fully. It is the precision weight of a kriging estimate whose nugget is
``h²``: the offset field ``m - s`` is itself uncertain at the scale of the single-view
error, so a very precise point cannot take all the weight (``c <= 1``). Points without a
std (NaN) keep weight 1. ``h = 0`` switches it off (the paper's weights).
"""

from __future__ import annotations

import numpy as np


def precision_weights(relative_std: np.ndarray | None, half_weight: float) -> np.ndarray | None:
    """HxW factors ``h² / (h² + r²)`` in (0, 1] (NaN where ``r`` is NaN), or None (off).

    None when ``half_weight`` is 0 or there is no std (the sweep without one, a graph
    without the ``depth_std`` topic): the interpolation then uses the paper's weights.
    """
    if half_weight <= 0 or relative_std is None:
        return None
    r = np.asarray(relative_std, dtype=np.float64)
    with np.errstate(invalid='ignore'):
        r = np.where(r >= 0, r, np.nan)  # a negative std is not a std: no evidence
    h2 = float(half_weight) ** 2
    return (h2 / (h2 + r * r)).astype(np.float32)


def check_half_weight(half_weight: float) -> None:
    """Raise a one-line ``ValueError`` unless ``half_weight`` is a finite number >= 0."""
    if not (np.isfinite(half_weight) and half_weight >= 0):
        raise ValueError(f'std_half_weight must be a finite relative std >= 0 (0: off), got {half_weight}')
