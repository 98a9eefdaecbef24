"""The fused depth's output contract: every pixel is a positive finite depth or NaN (REP 117).

The fusion's fallbacks hand the single-view map on as it came, and a network, a TorchScript
model or a test input can hold ``-1`` (a "no depth" code), ``0`` or ``±inf``. A consumer of
``depth_fusion/fused/depth`` (a TSDF, a point cloud, a planner) must never see those as
depths, so whatever path produced a keyframe's depth, it passes through
:func:`sanitize_depth` last. It is a separate function so each fallback (present or added
later) needs one call, not its own checks.
"""

from __future__ import annotations

import numpy as np


def sanitize_depth(depth: np.ndarray) -> tuple[np.ndarray, int]:
    """``(float32 copy with every non-finite or non-positive pixel set to NaN, how many were)``.

    NaN pixels already NaN are not counted: the count says how many *invalid values* the
    input held, so a caller can report them (a fallback that carried ``inf`` along).
    """
    out = np.array(depth, dtype=np.float32, copy=True)
    with np.errstate(invalid='ignore'):
        bad = ~np.isnan(out) & ~(np.isfinite(out) & (out > 0))
    count = int(bad.sum())
    if count:
        out[bad] = np.nan
    return out, count
