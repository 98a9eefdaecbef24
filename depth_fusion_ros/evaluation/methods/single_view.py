"""Evaluation methods of the single_view stage (registered on import).

* ``single_view``: the single-view source of the run (``--single-view``): the shipped
  compact model (``default``), a model path (checkpoint, ONNX, ``torch.export`` .pt2,
  TorchScript), ``simulated``, or ``simulated_relative`` (the simulated prior as inverse
  depth with a random positive scale and shift per keyframe, what a disparity network gives).
* ``single_view_simulated``: always the simulated CNN prior (``singleview.simulated``).

The fusion methods reuse the same prediction through ``single_view_prediction(ctx)``, which
memoises it per keyframe (and the loaded network per run), so a network runs once per frame
whatever the number of methods. Simulated-prior parameters come from ``--set
simulated.<field>=value`` (``SimulatedPriorConfig`` fields).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...singleview.predictor import SIMULATED_RELATIVE_SPEC, SIMULATED_SPEC, DepthPredictor, load_predictor
from ...singleview.simulated import SimulatedPriorConfig, simulate_prior, to_relative_inverse
from ..context import KeyframeContext
from ..registry import MethodOutput, register_method

#: ``--set simulated.<field>=...`` overrides the simulated prior's parameters.
SIMULATED_STAGE = 'simulated'


@dataclass
class SingleViewPrediction:
    """Single-view output at the working resolution.

    ``depth`` holds the source's values as they are: metres for ``metric_depth``; for
    ``relative_depth`` / ``inverse_depth`` an unknown scale (and shift), which the fusion's
    RANSAC fit maps to metric. Dense (no NaN).
    """

    depth: np.ndarray
    output_kind: str


def _model(ctx: KeyframeContext, source: str) -> DepthPredictor:
    device = ctx.options.device
    return ctx.shared_cached(f'single_view_model:{source}:{device}', lambda: load_predictor(source, device))


def _simulated(ctx: KeyframeContext) -> SingleViewPrediction:
    gt = ctx.gt_depth_working
    if gt is None:
        raise ValueError(
            f'{ctx.sequence.name}: frame {ctx.index} has no ground-truth depth '
            '(the simulated prior is made from it)'
        )
    cfg = SimulatedPriorConfig.from_dict(ctx.stage_params(SIMULATED_STAGE))
    sim = simulate_prior(gt, ctx.frame.rgb, cfg, seed=(int(ctx.options.seed), int(ctx.index)))
    return SingleViewPrediction(sim.depth, 'metric_depth')


def _simulated_relative(ctx: KeyframeContext) -> SingleViewPrediction:
    """The simulated prior as a disparity network would give it: inverse depth with a seeded
    random positive scale and shift per keyframe (the fusion must find both)."""
    metric = single_view_prediction(ctx, SIMULATED_SPEC).depth
    rel = to_relative_inverse(metric, seed=(int(ctx.options.seed), int(ctx.index), 1))
    return SingleViewPrediction(rel.inverse, 'inverse_depth')


def _network(ctx: KeyframeContext, source: str) -> SingleViewPrediction:
    predictor = _model(ctx, source)
    depth = predictor.predict(ctx.frame.rgb)
    size = (ctx.camera.width, ctx.camera.height)
    if depth.shape[::-1] != size:
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_LINEAR)
    return SingleViewPrediction(depth.astype(np.float32), predictor.output_kind)


def single_view_prediction(ctx: KeyframeContext, source: str | None = None) -> SingleViewPrediction:
    """The single-view prediction of this keyframe from ``source`` (default: the run's
    ``options.single_view``), computed once per keyframe and source."""
    src = str(source if source is not None else ctx.options.single_view)
    if src == SIMULATED_SPEC:
        return ctx.cached('single_view:simulated', lambda: _simulated(ctx))
    if src == SIMULATED_RELATIVE_SPEC:
        return ctx.cached('single_view:simulated_relative', lambda: _simulated_relative(ctx))
    return ctx.cached(f'single_view:{src}', lambda: _network(ctx, src))


def median_align(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, float]:
    """``pred`` scaled so its median matches the ground truth's on their common valid pixels."""
    valid = np.isfinite(gt) & (gt > 0) & np.isfinite(pred) & (pred > 0)
    if not valid.any():
        return np.full_like(pred, np.nan), float('nan')
    factor = float(np.median(gt[valid]) / np.median(pred[valid]))
    return (pred * factor).astype(np.float32), factor


def to_metric(
    pred: SingleViewPrediction, gt_working: np.ndarray | None
) -> tuple[np.ndarray, dict[str, float]]:
    """Metric depth for scoring: metric outputs as they are; relative outputs (and the
    reciprocal of inverse outputs) median-scaled to the ground truth."""
    if pred.output_kind == 'metric_depth':
        return pred.depth, {}
    if gt_working is None:
        raise ValueError(f'a {pred.output_kind} model needs ground truth to be scored (median scaling)')
    depth = pred.depth
    if pred.output_kind == 'inverse_depth':
        with np.errstate(divide='ignore'):
            depth = np.where(depth > 0, 1.0 / depth, np.nan).astype(np.float32)
    aligned, factor = median_align(depth, gt_working)
    return aligned, {'median_scale': factor}


@register_method(
    'single_view',
    'single-view depth of --single-view (default: the shipped compact CNN trained on synthetic data; '
    "'simulated': the simulated prior; 'simulated_relative': it as inverse depth up to scale and shift); "
    'metric outputs scored as they are, relative/inverse outputs '
    'after per-frame median scaling to the ground truth',
)
def single_view(ctx: KeyframeContext) -> MethodOutput:
    pred = single_view_prediction(ctx)
    depth, extras = to_metric(pred, ctx.gt_depth_working)
    return MethodOutput(depth, extras)


@register_method(
    'single_view_simulated',
    'simulated CNN prior from the ground truth: per-superpixel scale/offset errors, smooth deformation '
    'and noise (paper §III, Fig. 2); for measuring the fusion independently of network quality',
)
def single_view_simulated(ctx: KeyframeContext) -> MethodOutput:
    return MethodOutput(single_view_prediction(ctx, SIMULATED_SPEC).depth)
