"""The filter's published estimate as a ``MultiViewResult``, so selection and fusion work unchanged.

Field by field (a pixel is published once its inlier ratio, its number of measurements and
its relative inverse-depth std pass the ``filter.*`` thresholds):

* ``depth`` = ``1 / mu``; ``depth_std`` = ``sqrt(sigma^2 + b^2) / mu^2`` (m): the posterior
  std and the bias ``b`` an uncertain focal length may give the estimate under this motion
  (``focal_bias.py``; the posterior's own ``sigma`` is ``variance``), and ``bias_std`` =
  ``b / mu^2``, the share of it every estimate has in common;
* ``geometric_score`` = ``1 / sigma`` (the posterior inverse-depth std: every frame that
  matched it adds its ``J^2 / pixel_sigma^2``, as the sweep's one-pixel score sums its
  neighbours' ``J^2``);
* ``photometric_score`` = the inlier ratio ``a / (a + b)``: how often the pixel's patch was
  found where the estimate says (the filter's analogue of a distinct photometric minimum);
* ``score`` = ``inlier_ratio * geometric_score ** SIGMA_POWER * (mu / sigma) ** p`` with
  ``p = filter.score_relative_power`` (``SIGMA_POWER = 0`` and ``p = 0`` by default: the
  inlier ratio alone, see below): what stage 1 of the point selection ranks by;
* ``cost`` = the last matching cost ``1 - ZNCC``;
* and, beyond ``MultiViewResult``: ``variance`` (inverse depth squared), ``inlier_ratio`` and
  ``updates`` (measurements fused), for fusion weights and diagnostics.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from ..camera import PinholeCamera
from .semidense import MultiViewResult

#: ``score = inlier_ratio * sigma^-SIGMA_POWER``. 0: the posterior std is left out of the
#: ranking. It mostly says how long a region has been observed, so ranking by it packs the
#: stage-1 points into one part of the image (synthetic room: row spread 20-29 px instead of
#: 70) and the fusion then extrapolates from there (fused MAE 0.45 m against 0.32 m with 0).
SIGMA_POWER = 0.0


@dataclass
class FilterResult(MultiViewResult):
    """``MultiViewResult`` plus the filter's per-pixel posterior (NaN where no estimate)."""

    variance: np.ndarray | None = None
    inlier_ratio: np.ndarray | None = None
    updates: np.ndarray | None = None
    #: Set when nothing was published because under ``filter.min_published_fraction`` of the
    #: measured estimates passed the precision test: that share (the node notes it).
    withheld_fraction: float | None = None
    #: The part of ``depth_std`` (m) that an uncertain focal length's bias gives the estimate
    #: (``focal_bias.py``; NaN where no estimate, None when the filter adds none). Every
    #: estimate of a keyframe shares it, so averaging points does not remove it.
    bias_std: np.ndarray | None = None
    method: ClassVar[str] = 'filter'


def assemble_result(
    camera: PinholeCamera,
    target: torch.Tensor,
    mu: torch.Tensor,
    var: torch.Tensor,
    inlier: torch.Tensor,
    updates: torch.Tensor,
    cost: torch.Tensor,
    candidates: torch.Tensor,
    relative_power: float = 0.0,
    withheld_fraction: float | None = None,
    extra_variance: torch.Tensor | None = None,
) -> FilterResult:
    """Scatter published estimates (flat pixel indices ``target``) into NaN-filled (H, W) maps;
    ``withheld_fraction`` as :attr:`FilterResult.withheld_fraction`; ``extra_variance`` (inverse
    depth squared, per estimate) is added to ``var`` in ``depth_std`` only."""
    shape = (camera.height, camera.width)
    idx = target.cpu().numpy()

    def image(values: torch.Tensor) -> np.ndarray:
        out = np.full(shape[0] * shape[1], np.nan, dtype=np.float32)
        out[idx] = values.detach().cpu().numpy().astype(np.float32)
        return out.reshape(shape)

    sigma = torch.sqrt(var)
    geometric = 1.0 / torch.clamp(sigma, min=1e-12)
    return FilterResult(
        depth=image(1.0 / mu),
        depth_std=image((sigma if extra_variance is None else torch.sqrt(var + extra_variance)) / (mu * mu)),
        photometric_score=image(inlier),
        geometric_score=image(geometric),
        score=image(inlier * geometric**SIGMA_POWER * (mu / torch.clamp(sigma, min=1e-12)) ** relative_power),
        cost=image(cost),
        candidates=candidates.cpu().numpy().reshape(shape),
        camera=camera,
        distinctiveness=image(inlier),
        sharpness=np.full(shape, np.nan, dtype=np.float32),
        variance=image(var),
        inlier_ratio=image(inlier),
        updates=image(updates.to(mu.dtype)),
        withheld_fraction=withheld_fraction,
        bias_std=None if extra_variance is None else image(torch.sqrt(extra_variance) / (mu * mu)),
    )


def fill_missing(primary: FilterResult, extra: FilterResult) -> FilterResult:
    """``primary`` with its pixels without an estimate taken from ``extra`` (same camera).

    The fixed-lag read of the offline evaluation (:mod:`.filter_stream`): the estimate of a
    frame after the look-ahead, completed by what earlier filter keyframes held of the pixels
    that have since left the view.
    """
    take = ~np.isfinite(primary.depth) & np.isfinite(extra.depth)
    if not take.any():
        return primary
    maps = {}
    for f in dataclasses.fields(primary):
        a, b = getattr(primary, f.name), getattr(extra, f.name)
        if isinstance(a, np.ndarray) and a.dtype != bool and isinstance(b, np.ndarray):
            maps[f.name] = np.where(take, b, a).astype(a.dtype)
    maps['candidates'] = primary.candidates | extra.candidates
    return dataclasses.replace(primary, **maps)
