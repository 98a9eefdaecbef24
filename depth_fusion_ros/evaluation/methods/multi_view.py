"""Evaluation methods of the multi_view stage (registered on import).

* ``multi_view``: the semi-dense estimate (sparse: scored on its pixels; the harness adds
  ``density``);
* ``multi_view_selected``: the stage-1 points (the method's rule, multiview/stage1.py: the
  sweep's best ``select_fraction`` by photometric x geometric score, every estimate of the
  filter; ``--set fusion.stage1=`` overrides), sparse;
* ``tv``: the dense DTAM-style TV-regularised baseline over the same neighbours.

The fusion methods reuse the per-keyframe result through :func:`multi_view_result` and the
neighbours through :func:`neighbour_indices`. Options honoured: ``--neighbour-mode``,
``--neighbours``, ``--device``, and ``--set multi_view.<field>=...`` (``MultiViewConfig``),
``--set neighbours.<field>=...`` (``NeighbourConfig``), ``--set tv.<field>=...`` (``TVConfig``),
``--set multi_view.method=filter|sweep``: ``filter``, the default, is the temporal depth filter
run over *every* frame of the sequence up to each keyframe, in order (``--set
filter.<field>=...``, ``FilterConfig``); ``sweep`` is the paper's per-keyframe search over the
selected neighbours. The filter is the default because its fused depth is better on every
sequence we hold (docs/multi_view.md, "Verdict").
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ...multiview.filter_config import MULTI_VIEW_METHODS, FilterConfig
from ...multiview.filter_stream import FilterStream
from ...multiview.neighbours import NeighbourConfig, select_neighbours
from ...multiview.params import apply_overrides
from ...multiview.semidense import MultiViewConfig, MultiViewResult, empty_result, estimate_semidense
from ...multiview.tv import TVConfig, estimate_tv
from ..context import KeyframeContext, keyframe_indices
from ..focal import checked_uncertainty
from ..registry import MethodOutput, register_method

log = logging.getLogger(__name__)

#: ``--set <stage>.<field>=value`` stages read here.
MULTI_VIEW_STAGE = 'multi_view'
NEIGHBOURS_STAGE = 'neighbours'
TV_STAGE = 'tv'
FILTER_STAGE = 'filter'
#: ``--set multi_view.method=sweep|filter``: not a ``MultiViewConfig`` field, read here.
METHOD_PARAM = 'method'
#: The filter: better fused depth than the sweep on every sequence we hold (docs/multi_view.md,
#: "Verdict"); the same default as ``multi_view_node``'s ``multi_view.method``.
DEFAULT_METHOD = 'filter'
#: ``--neighbour-mode offline``: the filter's estimate of frame k is read after frame
#: k + ``neighbours.window`` (warped back into k), as the sweep then takes its neighbours from
#: ``window`` frames on both sides; online: causal.


def multi_view_method(ctx: KeyframeContext) -> str:
    """``sweep`` (the paper's per-keyframe search) or ``filter`` (the temporal depth filter)."""
    method = str(ctx.stage_params(MULTI_VIEW_STAGE).get(METHOD_PARAM, DEFAULT_METHOD))
    if method not in MULTI_VIEW_METHODS:
        raise ValueError(f'multi_view.method must be one of {", ".join(MULTI_VIEW_METHODS)}, got {method!r}')
    return method


def filter_config(ctx: KeyframeContext) -> FilterConfig:
    """``FilterConfig`` with the run's ``--set filter.*`` overrides (checked), its
    ``focal_uncertainty`` as the sequence's focal length check verified it (``evaluation/focal.py``)."""
    config = apply_overrides(FilterConfig(), ctx.stage_params(FILTER_STAGE), FILTER_STAGE)
    config.validate()
    verified = checked_uncertainty(ctx.shared, config.focal_uncertainty)
    return dataclasses.replace(config, focal_uncertainty=verified)


def multi_view_config(ctx: KeyframeContext) -> MultiViewConfig:
    """``MultiViewConfig`` with the run's ``--set multi_view.*`` overrides (checked)."""
    params = ctx.stage_params(MULTI_VIEW_STAGE)
    params.pop(METHOD_PARAM, None)
    config = apply_overrides(MultiViewConfig(), params, MULTI_VIEW_STAGE)
    config.validate()
    return config


def neighbour_config(ctx: KeyframeContext) -> NeighbourConfig:
    """``NeighbourConfig`` with the run's ``--set neighbours.*`` overrides (checked)."""
    config = apply_overrides(NeighbourConfig(), ctx.stage_params(NEIGHBOURS_STAGE), NEIGHBOURS_STAGE)
    config.validate()
    return config


def tv_config(ctx: KeyframeContext) -> TVConfig:
    """``TVConfig`` with the run's ``--set tv.*`` overrides (checked)."""
    config = apply_overrides(TVConfig(), ctx.stage_params(TV_STAGE), TV_STAGE)
    config.validate()
    return config


def neighbour_indices(ctx: KeyframeContext) -> list[int]:
    """Frame indices of the keyframe's neighbours (``--neighbour-mode``, ``--neighbours``).

    The table lives in the run's shared memo (one per sequence and settings), so every
    method and keyframe agrees on it.
    """
    mode, n = ctx.options.neighbour_mode, ctx.options.num_neighbours
    config = neighbour_config(ctx)
    table: dict[int, list[int]] = ctx.shared_cached(f'multi_view:neighbours:{mode}:{n}:{config}', dict)
    if ctx.index not in table:
        poses = ctx.sequence.poses
        table[ctx.index] = select_neighbours(poses, ctx.index, n, mode, ctx.camera, config)
    return table[ctx.index]


def _neighbour_views(ctx: KeyframeContext, indices: list[int]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    frames = ctx.sequence.frames
    return [frames[i].gray for i in indices], [frames[i].pose for i in indices]


def _filter_result(ctx: KeyframeContext) -> MultiViewResult:
    """The depth filter run over every frame of the sequence up to this keyframe, in order."""
    config, matching = filter_config(ctx), multi_view_config(ctx)
    frames = ctx.sequence.frames

    lookahead = neighbour_config(ctx).window if ctx.options.neighbour_mode == 'offline' else 0

    def make() -> FilterStream:
        return FilterStream(
            lambda i: (frames[i].gray, frames[i].pose),
            ctx.camera,
            config,
            matching,
            ctx.options.device,
            lookahead=lookahead,
            num_frames=len(frames),
            keyframes=keyframe_indices(len(frames), ctx.options),
        )

    stream = ctx.shared_cached(f'multi_view:filter:{config}:{matching}:{lookahead}', make)
    return stream.result_at(ctx.index)


def multi_view_result(ctx: KeyframeContext) -> MultiViewResult:
    """The multi-view estimate of this keyframe (sweep or filter), computed once per keyframe."""

    def compute() -> MultiViewResult:
        if multi_view_method(ctx) == 'filter':
            return _filter_result(ctx)
        indices = neighbour_indices(ctx)
        if not indices:
            log.warning(
                '%s: keyframe %d has no overlapping neighbour; no multi-view depth',
                ctx.sequence.name,
                ctx.index,
            )
            return empty_result(ctx.camera)
        grays, poses = _neighbour_views(ctx, indices)
        return estimate_semidense(
            ctx.frame.gray,
            ctx.frame.pose,
            grays,
            poses,
            ctx.camera,
            multi_view_config(ctx),
            device=ctx.options.device,
            neighbours=indices,
        )

    return ctx.cached('multi_view:result', compute)


@register_method(
    'multi_view',
    'semi-dense multi-view depth (multi_view.method: filter, the temporal inverse-depth filter, '
    'default; sweep, the ZNCC inverse-depth sweep over the selected neighbours)',
    sparse=True,
)
def multi_view(ctx: KeyframeContext) -> MethodOutput:
    result = multi_view_result(ctx)
    return MethodOutput(
        result.depth,
        {'n_estimates': float(result.valid.sum()), 'n_neighbours': float(len(result.neighbours))},
    )


@register_method(
    'multi_view_selected',
    'multi-view points kept by stage 1 (sweep: best fraction by photometric x geometric score; '
    'filter: every published estimate)',
    sparse=True,
)
def multi_view_selected(ctx: KeyframeContext) -> MethodOutput:
    """The points the fusion's stage 1 passes on, under the same ``--set fusion.stage1*``
    settings the ``fused`` method uses (one cached mask for both, so the row scores what was
    fused)."""
    from .fusion import _stage1, fusion_settings

    result = multi_view_result(ctx)
    mask = _stage1(ctx, result, fusion_settings(ctx)[1])
    depth = np.where(mask, result.depth, np.float32(np.nan)).astype(np.float32)
    return MethodOutput(depth, {'n_selected': float(mask.sum())})


@register_method('tv', 'dense DTAM-style multi-view depth: cost volume + Huber-TV (primal-dual)')
def tv(ctx: KeyframeContext) -> MethodOutput:
    indices = neighbour_indices(ctx)
    if not indices:
        log.warning('%s: keyframe %d has no overlapping neighbour; no TV depth', ctx.sequence.name, ctx.index)
        return MethodOutput(np.full((ctx.camera.height, ctx.camera.width), np.nan, dtype=np.float32))
    grays, poses = _neighbour_views(ctx, indices)
    depth = estimate_tv(
        ctx.frame.gray, ctx.frame.pose, grays, poses, ctx.camera, tv_config(ctx), device=ctx.options.device
    )
    return MethodOutput(depth, {'n_neighbours': float(len(indices))})
