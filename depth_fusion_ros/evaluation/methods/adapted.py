"""Evaluation methods of online adaptation, scored prequentially (registered on import).

* ``single_view_adapted`` — the single-view network (``--single-view``, one of our
  checkpoints) adapting online to the sequence;
* ``fused_adapted`` — the paper's fusion on that adapted single-view depth.

Prequential: keyframes are evaluated in order, and keyframe k is predicted by the network as
it was *before* it trained on keyframe k (it has seen keyframes < k only); then it trains on
k. The training signals are what the node graph has: the keyframe's multi-view result
(shared with ``multi_view`` / ``fused``) and its posed multi-view neighbours; never the ground
truth. As in the graph, a keyframe whose points the fusion's guard trusted none of, fusing the
prediction of that keyframe, is not trained on (``adaptation.follow_fusion_guard``,
adaptation/fusion_trust.py); that fusion is ``fused_adapted``'s own. Each sequence starts
again from the original network. ``--set adaptation.<field>=`` overrides ``AdaptConfig``
fields. ``depth-fusion adapt`` runs the same code to write a
checkpoint.

Per-frame extras: ``adapt_version`` (accepted updates so far), ``adapt_rolled_back``,
``adapt_skipped``, ``adapt_seconds`` (training time of the keyframe).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...adaptation.adapter import Adapter, UpdateReport
from ...adaptation.config import AdaptConfig
from ...adaptation.fusion_trust import AS_IS, FusionTrust, fusion_trust
from ...adaptation.sample import AdaptSample, Neighbour, make_sample
from ...fusion.pipeline import FusionResult
from ...singleview.predictor import DepthPredictor
from ..context import KeyframeContext
from ..registry import MethodOutput, register_method
from .single_view import SingleViewPrediction

STAGE = 'adaptation'


@dataclass
class AdaptationRun:
    """The per-sequence state: the adapter and a predictor around its accepted weights."""

    adapter: Adapter
    predictor: DepthPredictor
    version: int = 0


def adaptation_config(ctx: KeyframeContext) -> AdaptConfig:
    """``AdaptConfig`` with the run's seed and ``--set adaptation.*`` overrides."""
    return AdaptConfig.from_dict({'seed': int(ctx.options.seed), **ctx.stage_params(STAGE)})


def adaptation_run(ctx: KeyframeContext) -> AdaptationRun:
    def start() -> AdaptationRun:
        adapter = Adapter.from_spec(ctx.options.single_view, adaptation_config(ctx), ctx.options.device)
        return AdaptationRun(adapter, adapter.predictor())

    return ctx.shared_cached('adaptation:run', start)


def keyframe_sample(ctx: KeyframeContext, config: AdaptConfig, trust: FusionTrust = AS_IS) -> AdaptSample:
    """The keyframe's training signals: its selected multi-view points and posed neighbours;
    ``trust``: the fusion's reason for trusting none of them ('' when it did) and the factor it
    moved them by (``fusion_trust.py``)."""
    from .multi_view import multi_view_result, neighbour_indices

    mv = multi_view_result(ctx)
    frames = ctx.sequence.frames
    neighbours = [Neighbour(frames[j].rgb, frames[j].pose) for j in neighbour_indices(ctx)]
    return make_sample(
        ctx.index,
        ctx.frame.rgb,
        ctx.camera,
        mv.depth,
        mv.score,
        select_fraction=config.select_fraction,
        holdout_fraction=config.holdout_fraction,
        seed=config.seed,
        pose=ctx.frame.pose,
        neighbours=neighbours,
        mv_std=mv.depth_std,
        max_relative_std=config.max_relative_std,
        untrusted=trust.untrusted,
        points_scale=trust.points_scale,
    )


def observe_keyframe(ctx: KeyframeContext, run: AdaptationRun, trust: FusionTrust = AS_IS) -> UpdateReport:
    """Train on this keyframe (``trust``: see :func:`keyframe_sample`); refresh the predictor
    when the update was kept."""
    report = run.adapter.observe(keyframe_sample(ctx, run.adapter.config, trust))
    if run.adapter.version != run.version:
        run.predictor = run.adapter.predictor()
        run.version = run.adapter.version
    return report


Adapted = tuple[SingleViewPrediction, UpdateReport, FusionResult | None]


def adapted_prediction(ctx: KeyframeContext) -> Adapted:
    """Prediction of the weights from before this keyframe, its fusion when the guard's trust
    is followed (``fused_adapted``'s; None otherwise), then the update on it (once)."""
    from .fusion import fuse_automatic

    def compute() -> Adapted:
        run = adaptation_run(ctx)
        depth = run.predictor.predict(ctx.frame.rgb)
        size = (ctx.camera.width, ctx.camera.height)
        if depth.shape[::-1] != size:
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_LINEAR)
        prediction = SingleViewPrediction(depth.astype(np.float32), run.predictor.output_kind)
        fused, trust = None, AS_IS
        if run.adapter.config.follow_fusion_guard:
            fused = fuse_automatic(ctx, prediction.depth, prediction.output_kind, source='adapted')
            trust = fusion_trust(fused.decision, fused.decision_reason, fused.withheld, fused.evidence)
        report = observe_keyframe(ctx, run, trust)
        return prediction, report, fused

    return ctx.cached('adaptation:prediction', compute)


def _extras(report: UpdateReport) -> dict[str, float]:
    return {
        'adapt_version': float(report.version),
        'adapt_rolled_back': float(report.status == 'rolled_back'),
        'adapt_skipped': float(report.status == 'skipped'),
        'adapt_seconds': float(report.seconds),
    }


@register_method(
    'single_view_adapted',
    'single-view network adapting online (multi-view points + photometric consistency with posed '
    'neighbours, replay, guard); prequential: keyframe k predicted before training on it',
)
def single_view_adapted(ctx: KeyframeContext) -> MethodOutput:
    prediction, report, _ = adapted_prediction(ctx)
    return MethodOutput(prediction.depth, _extras(report))


@register_method(
    'fused_adapted',
    'fusion (automatic selection) on the online-adapted single-view depth, prequential',
)
def fused_adapted(ctx: KeyframeContext) -> MethodOutput:
    from .fusion import _output, fuse_automatic

    prediction, report, fused = adapted_prediction(ctx)
    if fused is None:  # the adaptation did not follow the guard: this keyframe's fusion not made yet
        fused = fuse_automatic(ctx, prediction.depth, prediction.output_kind, source='adapted')
    out = _output(fused)
    out.extras.update(_extras(report))
    return out
