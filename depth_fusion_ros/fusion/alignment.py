"""Relative single-view depth made metric by the multi-view points (stage 2's fit, applied).

Modern monocular networks often predict depth only up to an unknown affine map: MiDaS,
DPT and Depth Anything v1/v2 output *disparity* (inverse depth up to scale and shift),
others relative depth. The multi-view points are metric (or in the SLAM's units), so each
keyframe's scale and shift are found from them, in the model's **own space**:

* ``relative_depth``: ``m ≈ a·s + b`` (depth space);
* ``inverse_depth``:  ``1/m ≈ a·s + b`` (inverse-depth space: the shift of a disparity
  model is a shift of inverse depth, so fitting it in depth space would bend the map);
* ``metric_depth``: ``m ≈ a·s`` (only when aligning is asked for, e.g. a monocular SLAM).

The fit is robust and per keyframe: RANSAC over the stage-1 points (two-point hypotheses in
the model's space, residuals in metres of depth so one threshold serves every kind), then
least squares in the model's space on the inliers until they stop changing
(:func:`depth_fusion_ros.fusion.selection.fit_ransac`). Its inliers are Ω, the points the
fusion interpolates (paper §III-D: the same fit selects and maps).

Applying the fit can give a non-positive value where the network's relative output lies
outside the range the points constrain (a disparity below the fitted shift is "beyond
infinity"). Those pixels have no depth: they become NaN and are counted
(``AlignedDepth.n_nonpositive``), never clamped to a made-up depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .selection import MIN_DEPTH, LinearFit, check_output_kind, fit_least_squares, fit_ransac

if TYPE_CHECKING:
    from .pipeline import FusionConfig

#: Inverse-depth fits: a positive value below ``1 / (FAR_FACTOR x farthest inlier)`` maps
#: to that far depth (the points say nothing about what lies ten times beyond them).
FAR_FACTOR = 10.0


def fit_space(output_kind: str) -> str:
    """The space the fit works in: ``'inverse_depth'`` for disparity-like outputs, else ``'depth'``."""
    check_output_kind(output_kind)
    return 'inverse_depth' if output_kind == 'inverse_depth' else 'depth'


@dataclass
class AlignedDepth:
    """The single-view map in metres after the fit (float32 HxW).

    NaN where the input was NaN or the fitted value was not positive; ``n_nonpositive``
    counts the latter.
    """

    depth: np.ndarray
    n_nonpositive: int


def fit_alignment(
    s: np.ndarray,
    m: np.ndarray,
    output_kind: str,
    config: FusionConfig,
    *,
    robust: bool = True,
) -> LinearFit:
    """Per-keyframe fit of the single-view values ``s`` to the multi-view depths ``m`` (paired
    1-D samples) in the model's own space.

    ``robust``: RANSAC then least squares on the inliers (stage 2; its inliers are Ω).
    ``robust=False``: least squares on points already known to be good (a given Ω, e.g. the
    oracle). The model (affine or scale) and the plausible scales come from ``config``.
    """
    inverse = fit_space(output_kind) == 'inverse_depth'
    affine = config.model(output_kind) == 'affine'
    if not robust:
        return fit_least_squares(s, m, inverse=inverse, affine=affine)
    return fit_ransac(
        s,
        m,
        threshold=config.ransac_threshold,
        relative=config.ransac_relative,
        iterations=config.ransac_iterations,
        min_inliers=config.ransac_min_inliers,
        seed=config.seed,
        inverse=inverse,
        affine=affine,
        scale_range=config.scale_range(output_kind),
    )


def apply_alignment(s: np.ndarray, fit: LinearFit) -> AlignedDepth:
    """Depth in metres from single-view values ``s`` through ``fit``.

    ``a·s + b ≤ 0`` (non-positive depth, or inverse depth) is NaN and counted. For inverse
    fits, tiny positive inverse depths map at most to ``FAR_FACTOR`` x the farthest inlier.
    Positive depths are at least :data:`MIN_DEPTH`.
    """
    s = np.asarray(s, dtype=np.float64)
    lin = fit.a * s + fit.b
    with np.errstate(invalid='ignore'):
        nonpositive = np.isfinite(lin) & (lin <= 0)
    if fit.inverse:
        far = FAR_FACTOR * fit.max_depth if np.isfinite(fit.max_depth) else 1e3
        with np.errstate(divide='ignore', invalid='ignore'):
            depth = np.minimum(1.0 / lin, far)
    else:
        depth = lin
    with np.errstate(invalid='ignore'):
        depth = np.maximum(depth, MIN_DEPTH)
    depth[nonpositive | ~np.isfinite(lin)] = np.nan
    return AlignedDepth(depth.astype(np.float32), int(nonpositive.sum()))
