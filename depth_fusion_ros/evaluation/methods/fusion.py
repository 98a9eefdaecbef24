"""Evaluation methods of the fusion stage (registered on import).

* ``fused`` — the paper's method: stage-1 (best ``stage1_fraction`` by score) and stage-2
  (RANSAC) point selection, then the interpolation with all four weights;
* ``fused_fast`` — the same in the fast mode (the harness then measures fast vs exact);
* ``fused_unguarded`` — ``fused`` without the guard (``fusion.guard=false``) or the halo test
  (``fusion.halo_min_step=0``, ``fusion/occlusion.py``) and with the
  paper's weights as written (``fusion.structure_scale=1``): the paper's fusion as it was,
  to compare with;
* ``fused_oracle`` — Ω = the multi-view points within ``oracle_threshold`` (10 cm) of the
  ground truth, as the paper's right-hand table (an upper bound of the selection), with the
  paper's weights as written (``structure_scale`` 1, no ``certainty_floor`` or
  ``certainty_gain``: the oracle of issue 11's targets);
* ``fused_w1``, ``fused_w1w2`` — oracle points with the weights W1, W1·W2 only (Table III;
  ``fused_oracle`` is its "all four" column), the paper's normalisation as written.

The single-view source is the run's ``--single-view`` (``ctx.options.single_view``). The
``fusion`` stage parameters (``--set fusion.KEY=VALUE``) override ``FusionConfig`` fields,
plus ``stage1_fraction``, ``stage1`` (``auto|fraction|all``, multiview/stage1.py) and
``oracle_threshold``. A method's own setting (the mode of ``fused_fast``, the weights of the
ablation) wins over the overrides. The weight kernel is compiled with ``torch.compile`` here
unless ``fusion.compile_kernel=false``: an evaluation
runs hundreds of keyframes, so the one-off compile pays for itself many times.

Per-frame extras: ``n_stage1``, ``n_omega`` (the points fused), ``fallback`` (1 when the
frame fell back to the single-view depth), ``scale_a``/``offset_b`` (the stage-2 line),
``n_nonpositive`` (pixels the alignment of a relative source mapped to a non-positive depth:
NaN, uncovered), ``withheld`` (1 when the keyframe has no depth at all: a source that needs
the alignment and has no trusted one; it is then scored on no pixel, and the report's guard
table counts it), the guard's ``decision`` (index into ``guard.DECISIONS``: 0 full ... 4
single-view) and ``keyframe_confidence``, ``certainty`` (the mean share of the correction
the certainty floor kept) and ``certainty_floor`` (the κ this keyframe used, in units of one
point's largest weight; both NaN where the keyframe was not interpolated) and ``stream_scale``
(the factor the metric single view was scaled by into the points' unit,
``fusion/stream_scale.py``; 1 until taken, ``--set stream_scale.*``) and ``scale_jump`` (the
keyframe's log factor less the stream's, NaN until judged; beyond ``stream_scale.max_jump``
the keyframe keeps its single view). ``--set
guard.<GuardConfig field>=...`` sets its thresholds; the automatic methods give it the
multi-view result's per-pixel evidence (``depth_std``, and the neighbour agreement when the
multi-view stage provides one). ``--set consistency.<field>=...``
sets stage 3 of the selection (``fusion/consistency.py``; off by default, the paper's two
stages); ``fused_consistent`` is ``fused`` with it on.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from ...fusion.consistency import ConsistencyConfig
from ...fusion.guard import DECISIONS, GuardConfig, MultiViewEvidence
from ...fusion.pipeline import FusionConfig, FusionResult, fuse_keyframe
from ...fusion.stream_scale import StreamScale, StreamScaleConfig
from ...multiview.params import apply_overrides
from ..context import KeyframeContext
from ..distance_bands import band_sums
from ..registry import MethodOutput, register_method

log = logging.getLogger(__name__)

STAGE = 'fusion'
GUARD_STAGE = 'guard'
CONSISTENCY_STAGE = 'consistency'
STREAM_SCALE_STAGE = 'stream_scale'
#: The paper's oracle: multi-view points whose error against ground truth is below 10 cm.
DEFAULT_ORACLE_THRESHOLD = 0.10
#: Evaluation defaults that differ from ``FusionConfig``'s.
EVALUATION_DEFAULTS: dict[str, Any] = {'compile_kernel': True}


def fusion_settings(ctx: KeyframeContext, **forced: Any) -> tuple[FusionConfig, dict[str, Any]]:
    """``FusionConfig`` from the evaluation defaults, ``--set fusion.*`` and ``forced``; plus
    the method-level settings (``stage1_fraction``, ``stage1``, ``oracle_threshold``)."""
    from .multi_view import multi_view_config

    params = {'device': ctx.options.device, 'seed': int(ctx.options.seed), **EVALUATION_DEFAULTS}
    params.update(ctx.stage_params(STAGE))
    # multi_view.select_fraction is the same setting seen from the multi-view side (the
    # node's fusion.stage1_fraction defaults to it too): fusion.stage1_fraction wins.
    extra = {
        'stage1_fraction': float(params.pop('stage1_fraction', multi_view_config(ctx).select_fraction)),
        'oracle_threshold': float(params.pop('oracle_threshold', DEFAULT_ORACLE_THRESHOLD)),
        'stage1': str(params.pop('stage1', 'auto')),
    }
    params.update(forced)
    known = {f.name for f in dataclasses.fields(FusionConfig)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(
            f'unknown fusion parameter(s) {", ".join(unknown)}; known: '
            f'{", ".join(sorted(known | set(extra)))}'
        )
    return FusionConfig(**params), extra


def guard_settings(ctx: KeyframeContext) -> GuardConfig:
    """``GuardConfig`` with the run's ``--set guard.*`` overrides (checked)."""
    return apply_overrides(GuardConfig(), ctx.stage_params(GUARD_STAGE), GUARD_STAGE)


def consistency_settings(ctx: KeyframeContext) -> ConsistencyConfig:
    """``ConsistencyConfig`` (stage 3) with the run's ``--set consistency.*`` overrides (checked)."""
    return apply_overrides(ConsistencyConfig(), ctx.stage_params(CONSISTENCY_STAGE), CONSISTENCY_STAGE)


def stream_scale_settings(ctx: KeyframeContext) -> StreamScaleConfig:
    """``StreamScaleConfig`` with the run's ``--set stream_scale.*`` overrides (checked)."""
    return apply_overrides(StreamScaleConfig(), ctx.stage_params(STREAM_SCALE_STAGE), STREAM_SCALE_STAGE)


def sequence_scale(ctx: KeyframeContext, source: str) -> StreamScale:
    """The fusion node's stream scale (``fusion/stream_scale.py``) over this sequence's
    keyframes, one per single-view ``source`` (the run's, the adapting network's); each
    keyframe is taken once however many methods fuse it (keyed by its index)."""
    return ctx.shared_cached(f'stream_scale:{source}', lambda: StreamScale(stream_scale_settings(ctx)))


def _inputs(ctx: KeyframeContext) -> tuple[np.ndarray, str, Any]:
    """Single-view depth and kind, and the multi-view result of this keyframe (shared caches)."""
    from .multi_view import multi_view_result
    from .single_view import single_view_prediction

    prediction = single_view_prediction(ctx)
    return prediction.depth, prediction.output_kind, multi_view_result(ctx)


def _stage1(ctx: KeyframeContext, mv: Any, extra: dict[str, Any]) -> np.ndarray:
    """Stage-1 points: ``--set fusion.stage1=auto|fraction|all`` (auto: the multi-view
    method's rule, multiview/stage1.py) with ``fusion.stage1_fraction``."""
    rule, fraction = extra['stage1'], extra['stage1_fraction']
    return ctx.cached(f'fusion:stage1:{rule}:{fraction}', lambda: mv.stage1_mask(rule, fraction))


def oracle_mask(mv_depth: np.ndarray, gt: np.ndarray | None, threshold: float) -> np.ndarray:
    """Multi-view pixels whose depth is within ``threshold`` metres of the ground truth."""
    if gt is None:
        raise ValueError('the oracle selection needs ground-truth depth, and this frame has none')
    if gt.shape != mv_depth.shape:
        raise ValueError(f'ground truth {gt.shape} and multi-view depth {mv_depth.shape} differ in size')
    with np.errstate(invalid='ignore'):
        return np.isfinite(mv_depth) & np.isfinite(gt) & (gt > 0) & (np.abs(mv_depth - gt) < threshold)


def _output(result: FusionResult) -> MethodOutput:
    extras = {
        'n_stage1': float(result.n_stage1),
        'n_omega': float(result.n_omega),
        'fallback': 0.0 if result.fallback is None else 1.0,
        'scale_a': float(result.a),
        'offset_b': float(result.b),
        'n_nonpositive': float(result.n_nonpositive),
        'decision': float(DECISIONS.index(result.decision)),
        'keyframe_confidence': float(result.keyframe_confidence),
        'withheld': float(result.withheld),
        'certainty': float(result.evidence.get('certainty', np.nan)),
        'certainty_floor': float(result.evidence.get('certainty_floor', np.nan)),
        'stream_scale': float(result.evidence.get('stream_scale', 1.0)),
        'scale_jump': float(result.evidence.get('scale_jump', np.nan)),
    }
    return MethodOutput(result.depth, extras)


def fused_automatic(ctx: KeyframeContext, **forced: Any) -> MethodOutput:
    """Fusion with the paper's automatic two-stage selection; its extras also hold the errors
    by distance to the nearest point of Ω (``evaluation.distance_bands``)."""
    result = fused_result(ctx, **forced)
    out = _output(result)
    gt = ctx.gt_depth_working
    if gt is not None:
        single = result.single_aligned if result.single_aligned is not None else _inputs(ctx)[0]
        out.extras.update(band_sums(single, result.depth, gt, result.omega_mask))
    return out


def fuse_automatic(
    ctx: KeyframeContext,
    single: np.ndarray,
    kind: str,
    stage3: bool | None = None,
    source: str = 'single_view',
    **forced: Any,
) -> FusionResult:
    """The automatic fusion of ``single`` (``kind`` units) with this keyframe's multi-view
    result, as the fusion node does it: the ``--set`` fusion, guard and stage-3 settings
    (``stage3`` overrides ``consistency.enabled``), the multi-view evidence (its std) and the
    stream's scale (:func:`sequence_scale`; ``source`` names the single view's stream)."""
    from .multi_view import multi_view_result

    config, extra = fusion_settings(ctx, **forced)
    mv = multi_view_result(ctx)
    consistency = consistency_settings(ctx)
    if stage3 is not None:
        consistency = dataclasses.replace(consistency, enabled=stage3)
    scale = sequence_scale(ctx, source)
    result = fuse_keyframe(
        single,
        mv.depth,
        _stage1(ctx, mv, extra),
        config,
        output_kind=kind,
        guard_config=guard_settings(ctx),
        evidence=MultiViewEvidence.from_result(mv),
        consistency_config=consistency,
        image=ctx.frame.gray,
        stream_scale=scale,
        stamp=ctx.index,
    )
    if result.stream_scale_found:
        name, index = ctx.sequence.name, ctx.index
        log.warning('%s (%s), keyframe at frame %d: %s', name, source, index, scale.describe())
    return result


def fused_result(ctx: KeyframeContext, **forced: Any) -> FusionResult:
    """The automatic fusion of this keyframe (memoised without ``forced``: ``map`` reuses it)."""

    def compute() -> FusionResult:
        single, kind, _ = _inputs(ctx)
        return fuse_automatic(ctx, single, kind, **forced)

    return ctx.cached('fusion:automatic', compute) if not forced else compute()


def fused_consistent(ctx: KeyframeContext) -> FusionResult:
    """``fused`` with stage 3 of the selection switched on (``--set consistency.*`` still apply)."""
    single, kind, _ = _inputs(ctx)
    return fuse_automatic(ctx, single, kind, stage3=True)


def fused_oracle(ctx: KeyframeContext, **forced: Any) -> MethodOutput:
    """Fusion with the oracle selection (ground-truth error below ``oracle_threshold``)."""
    config, extra = fusion_settings(ctx, **forced)
    single, kind, mv = _inputs(ctx)
    omega = ctx.cached(
        f'fusion:oracle:{extra["oracle_threshold"]}',
        lambda: oracle_mask(mv.depth, ctx.gt_depth_working, extra['oracle_threshold']),
    )
    result = fuse_keyframe(single, mv.depth, omega, config, output_kind=kind, omega_mask=omega)
    return _output(result)


def _register(name: str, description: str, fn: Callable[..., MethodOutput], **forced: Any) -> None:
    register_method(name, description)(lambda ctx: fn(ctx, **forced))


#: The paper's interpolation as written, for the methods that reproduce its tables: depths and
#: gradients in metres (no structure scale) and normalised weights with no certainty floor,
#: fixed or raised by the single view's precision.
PAPER_AS_WRITTEN = {'structure_scale': 1.0, 'certainty_floor': 0.0, 'certainty_gain': 0.0}

_register(
    'fused',
    'fusion with automatic point selection (stage 1 score + stage 2 RANSAC), paper §III',
    fused_automatic,
)
_register(
    'fused_fast',
    'as fused, fast mode (exact on a coarse grid + structure-guided upsampling)',
    fused_automatic,
    mode='fast',
)
_register(
    'fused_unguarded',
    "as fused without the guard or the halo test and in the paper's metres: every stage-2 point "
    'bends the depth',
    fused_automatic,
    guard=False,
    halo_min_step=0.0,
    **PAPER_AS_WRITTEN,
)
_register(
    'fused_consistent',
    'as fused with stage 3 of the selection on (consistency.enabled=true, fusion/consistency.py)',
    lambda ctx: _output(fused_consistent(ctx)),
)
_register(
    'fused_oracle',
    'fusion with oracle points (multi-view error < 10 cm against ground truth), all four weights, '
    "the paper's metres (structure_scale 1)",
    fused_oracle,
    weights='all',
    **PAPER_AS_WRITTEN,
)
_register(
    'fused_w1',
    'fusion with oracle points and the proximity weight W1 only (Table III)',
    fused_oracle,
    weights='w1',
    **PAPER_AS_WRITTEN,
)
_register(
    'fused_w1w2',
    'fusion with oracle points and the weights W1·W2 only (Table III)',
    fused_oracle,
    weights='w1w2',
    **PAPER_AS_WRITTEN,
)
