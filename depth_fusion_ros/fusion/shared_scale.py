"""How much of the points' global scale a keyframe takes when their error is partly shared.

Why: the fusion bends the single-view depth onto its multi-view points, and with them onto
their global scale. A point's standard deviation says how far it may be off, and the guard
trusts points whose deviation is small against the single view's error. But part of it can be
common to every point of the keyframe: under rotation-dominant motion an unverified focal
length slides every estimate along its line the same way (``multiview/focal_bias.py``), so the
points agree with each other, pass every test they can make among themselves, and all sit
10-20 % too near. Averaging many of them removes their own noise, not that bias. On a handheld
sweep with camera_info 5 % short (seed 311), eleven keyframes in a row were fused 1.08-1.50x
their input that way: the points' shared std read 0.15-0.17, the single view's error 0.08-0.12.

So the keyframe's global scale is weighed as two measurements of one number: the points',
uncertain by their shared std ``b`` (the median over the trusted points), and the single
view's, uncertain by ``n``. The points' scale enters with the weight

    w = n^2 / (n^2 + b^2)

(inverse-variance weighting): every point is moved by ``-(1 - w)`` of the log scale ``c`` the
points give the single view, so the interpolation takes ``w c`` of it and all of the points'
local shape. How far off the single view's scale is cannot be measured; ``n^2`` is the larger
of two lower bounds: its error about the points' shape (the guard's ``single_error`` ``e``: a
network that far off in shape is as far off in scale), and the part of the disagreement that
the points' shared std cannot explain (``c^2 - b^2``: a network off by a factor of three, as
the shipped one is on TUM fr1_xyz, still takes the points' scale in full). ``b = 0`` (a
verified focal length, a sweep, no filter) leaves the points as they are. A source that is
only metric through the points (relative or inverse depth) has no scale of its own to weigh,
and neither does a keyframe whose single-view error the guard could not read.
"""

from __future__ import annotations

import math

import numpy as np


def scale_weight(single_error: float, shared_std: float, scale: float) -> float:
    """``n^2 / (n^2 + b^2)`` with ``n^2 = max(e^2, c^2 - b^2)``, ``c = log(scale)``: the share of
    the points' global scale to take (1 when any of them is unknown or ``b`` is 0)."""
    e, b = float(single_error), float(shared_std)
    if not (math.isfinite(e) and math.isfinite(b) and math.isfinite(scale) and scale > 0) or b <= 0.0:
        return 1.0
    c = math.log(scale)
    n2 = max(e * e, c * c - b * b)
    return n2 / (n2 + b * b) if n2 > 0 else 0.0


def points_factor(scale: float, weight: float) -> float:
    """``scale^-(1 - weight)``: the factor that moves the points by ``1 - weight`` of the log of
    ``scale`` (their global scale against the single view), towards the single view's scale
    (1 where ``weight`` is 1 or more, or either is unknown). The fusion moves its points by it,
    and the adaptation its targets (``adaptation/fusion_trust.py``)."""
    if not (math.isfinite(scale) and scale > 0 and math.isfinite(weight)) or weight >= 1.0:
        return 1.0
    return math.exp(-(1.0 - max(weight, 0.0)) * math.log(scale))


def weighed_points(m: np.ndarray, factor: float) -> np.ndarray:
    """The multi-view depth ``m`` times :func:`points_factor` (``m`` itself for 1)."""
    if factor == 1.0:
        return m
    return (m * np.float32(factor)).astype(m.dtype, copy=False)
