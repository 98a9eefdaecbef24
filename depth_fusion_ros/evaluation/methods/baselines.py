"""Reference methods that bound the scale of the numbers: ``ground_truth`` and ``constant_median``."""

from __future__ import annotations

import numpy as np

from ..context import KeyframeContext
from ..registry import MethodOutput, register_method


@register_method('ground_truth', 'the ground truth itself (sanity check: every error is 0)')
def ground_truth(ctx: KeyframeContext) -> MethodOutput:
    if ctx.gt_depth is None:
        raise ValueError(f'{ctx.sequence.name}: frame {ctx.index} has no ground-truth depth')
    return MethodOutput(ctx.gt_depth.astype(np.float32))


@register_method(
    'constant_median',
    'every pixel at the median ground-truth depth of the frame (a floor every method must beat)',
)
def constant_median(ctx: KeyframeContext) -> MethodOutput:
    gt = ctx.gt_depth_working
    if gt is None:
        raise ValueError(f'{ctx.sequence.name}: frame {ctx.index} has no ground-truth depth')
    valid = gt[np.isfinite(gt) & (gt > 0)]
    value = float(np.median(valid)) if valid.size else np.nan
    return MethodOutput(np.full(gt.shape, value, dtype=np.float32))
