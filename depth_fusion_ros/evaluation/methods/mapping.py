"""Evaluation methods of the mapping stage: TSDF maps spanning the keyframes (registered on import).

* ``map`` — the fused depth of every keyframe (automatic selection, as ``fused``), weighted by
  its confidence, integrated with the ground-truth poses where it agrees with the keyframes
  around it (``map.consistency_*``, mapping/consistency.py);
* ``map_single_view`` — the single-view depth alone (weight 1);
* ``map_multi_view`` — the semi-dense multi-view depth alone (weight 1).

Each is scored once per sequence against a map integrated the same way (same keyframes,
poses, ``MapConfig``) from the ground-truth depth: accuracy (median / mean distance from map
points to the reference surface) and completeness (share of the reference surface within
5 cm / 10 cm of the map); see ``depth_fusion_ros.mapping.scoring``. The ``map`` stage
parameters (``--set map.voxel_size=0.02``) override ``MapConfig`` fields; the engine is
torch unless ``map.engine`` says otherwise. A picture of the maps (``<seq>_map.png``) goes
into the report.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ...mapping.config import MapConfig
from ...mapping.consistency import ConsistentMap
from ...mapping.engine import make_map
from ...mapping.render import map_figure
from ...mapping.scoring import score_map
from ..context import KeyframeContext, SequenceContext
from ..registry import MethodOutput, SequenceOutput, register_method

STAGE = 'map'
REFERENCE = 'ground truth'
#: Evaluation defaults that differ from ``MapConfig``'s: the confidence-weighted torch engine.
EVALUATION_DEFAULTS: dict[str, Any] = {'engine': 'torch'}


def map_config(ctx: KeyframeContext | SequenceContext) -> MapConfig:
    """``MapConfig`` from the evaluation defaults and ``--set map.*``."""
    params = {'device': ctx.options.device, **EVALUATION_DEFAULTS, **ctx.options.params.get(STAGE, {})}
    known = {f.name for f in dataclasses.fields(MapConfig)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f'unknown map parameter(s) {", ".join(unknown)}; known: {", ".join(sorted(known))}')
    return MapConfig(**params).validate()


def _map(ctx: KeyframeContext, label: str) -> ConsistentMap:
    """The sequence's map called ``label`` (created on first use). The ground-truth reference
    takes every pixel (no consistency test: it is the surface the others are scored against)."""
    config = map_config(ctx)
    if label == REFERENCE:
        config = dataclasses.replace(config, consistency_span=0)
    return ctx.shared_cached(f'map:{label}', lambda: make_map(config)[0])


def _integrate(ctx: KeyframeContext, label: str, depth: np.ndarray, confidence: np.ndarray | None) -> None:
    frame = ctx.frame
    _map(ctx, label).integrate(depth, frame.pose, ctx.camera, confidence=confidence, rgb=frame.rgb)
    _integrate_reference(ctx)


def _integrate_reference(ctx: KeyframeContext) -> None:
    """The ground-truth map gets each keyframe once, whichever map method asked first."""
    done = ctx.shared_cached('map:reference_keyframes', set)
    if ctx.index in done:
        return
    done.add(ctx.index)
    gt = ctx.gt_depth_working
    if gt is None:
        raise ValueError(f'{ctx.sequence.name}: frame {ctx.index} has no ground-truth depth for the map')
    frame = ctx.frame
    _map(ctx, REFERENCE).integrate(gt, frame.pose, ctx.camera, rgb=frame.rgb)


def _fused(ctx: KeyframeContext) -> MethodOutput:
    from .fusion import fused_result

    result = fused_result(ctx)
    _integrate(ctx, 'fused', result.depth, np.asarray(result.confidence, np.float32))
    return MethodOutput(result.depth)


def _single_view(ctx: KeyframeContext) -> MethodOutput:
    from .single_view import single_view_prediction

    prediction = single_view_prediction(ctx)
    if prediction.output_kind != 'metric_depth':
        raise ValueError(
            f'map_single_view needs metric single-view depth; {ctx.options.single_view!r} gives '
            f'{prediction.output_kind} (use map, whose fusion makes it metric)'
        )
    _integrate(ctx, 'single-view', prediction.depth, None)
    return MethodOutput(prediction.depth)


def _multi_view(ctx: KeyframeContext) -> MethodOutput:
    from .multi_view import multi_view_result

    depth = multi_view_result(ctx).depth
    _integrate(ctx, 'multi-view', depth, None)
    return MethodOutput(depth)


def _finish(label: str) -> Callable[[SequenceContext], SequenceOutput]:
    def finish(seq: SequenceContext) -> SequenceOutput:
        meshes = _meshes(seq)
        metrics = score_map(meshes[label], meshes[REFERENCE])
        engine = seq.shared[f'map:{label}']
        metrics['map_blocks'] = float(engine.n_blocks)
        metrics['map_evicted_blocks'] = float(engine.evicted_blocks)
        # Evicted blocks that are gone (no archive, the archive full): the map scored lacks them.
        metrics['map_lost_blocks'] = float(engine.lost_blocks)
        figure = seq.shared.setdefault('map:figure', _figure(seq))
        return SequenceOutput(metrics, figure, {'mesh': meshes[label]})

    return finish


def _meshes(seq: SequenceContext) -> dict[str, Any]:
    """Every map of the sequence as a mesh (extracted once), the reference first."""
    meshes = seq.shared.setdefault('map:meshes', {})
    for key, engine in list(seq.shared.items()):
        if key.startswith('map:') and hasattr(engine, 'mesh'):
            label = key[len('map:') :]
            if label not in meshes:
                engine.flush()  # the keyframes still waiting for successors that never came
                meshes[label] = engine.mesh()
    return dict(sorted(meshes.items(), key=lambda kv: kv[0] != REFERENCE))


def _figure(seq: SequenceContext) -> Callable[[Path], list[Path]]:
    def draw(out_dir: Path) -> list[Path]:
        middle = seq.keyframes[len(seq.keyframes) // 2]
        path = out_dir / f'{seq.sequence.name}_map.png'
        title = f'{seq.sequence.name}: TSDF maps of {len(seq.keyframes)} keyframes (ground-truth poses)'
        return [map_figure(_meshes(seq), seq.sequence.frames[middle].pose, seq.sequence.camera, path, title)]

    return draw


register_method(
    'map',
    'TSDF map of the fused depth (confidence-weighted), scored against the ground-truth-depth map',
    finish=_finish('fused'),
)(_fused)
register_method(
    'map_single_view',
    'TSDF map of the single-view depth alone, scored against the ground-truth-depth map',
    finish=_finish('single-view'),
)(_single_view)
register_method(
    'map_multi_view',
    'TSDF map of the semi-dense multi-view depth alone, scored against the ground-truth-depth map',
    finish=_finish('multi-view'),
)(_multi_view)
