"""A seeded uniform subsample of Ω: the one rule behind ``fusion.max_points`` and the guard's sample.

Both bound a cost that grows with |Ω| (the interpolation's pixels x points, the guard's
neighbour search) by looking at a uniform subset drawn from ``fusion.seed``, so a keyframe
fuses to the same numbers every time.
"""

from __future__ import annotations

import numpy as np


def seeded_subsample(count: int, size: int, seed: int) -> np.ndarray:
    """Sorted indices of ``size`` of ``count`` items (all of them when ``size >= count``),
    drawn without replacement from ``seed``."""
    if size >= count:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=int(size), replace=False))
