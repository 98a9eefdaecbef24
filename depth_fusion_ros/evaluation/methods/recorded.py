"""Methods that score what the ROS node graph published, read back from a recorded bag.

``depth-fusion run --record OUT`` writes the nodes' outputs into a rosbag2; these methods
look up, for each keyframe, the recorded depth whose header stamp is the frame's stamp, so
the output of the real node graph is scored exactly like the offline methods. The bag is
given with ``--set recorded.bag=OUT`` (or ``EvalOptions.params['recorded']['bag']``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...data.sequence import Sequence
from ..context import KeyframeContext
from ..registry import MethodOutput, register_method

#: Recorded topic of each method (defaults of the nodes, docs/nodes.md).
TOPICS = {
    'graph_fused': '/depth_fusion/fused/depth',
    'graph_single_view': '/depth_fusion/single_view/depth',
    'graph_multi_view': '/depth_fusion/multi_view/depth',
}
#: Largest difference between a frame's stamp and a recorded header stamp that still matches.
STAMP_TOLERANCE_NS = 1_000_000


def recorded_depths(bag: str | Path, topic: str) -> dict[int, np.ndarray]:
    from ...data.rosbag_read import read_depth_images

    return read_depth_images(bag, topic)


def match_stamps(frame_stamps: np.ndarray, recorded_ns: list[int]) -> dict[int, int]:
    """Frame index -> recorded stamp (ns) for every recorded stamp that matches a frame."""
    if not recorded_ns:
        return {}
    frame_ns = np.round(np.asarray(frame_stamps, dtype=np.float64) * 1e9).astype(np.int64)
    order = np.argsort(frame_ns)
    out: dict[int, int] = {}
    for ns in recorded_ns:
        k = int(np.searchsorted(frame_ns[order], ns))
        candidates = [order[j] for j in (k - 1, k) if 0 <= j < len(order)]
        best = min(candidates, key=lambda i: abs(int(frame_ns[i]) - ns))
        if abs(int(frame_ns[best]) - ns) <= STAMP_TOLERANCE_NS:
            out[int(best)] = ns
    return out


def recorded_keyframes(sequence: Sequence, bag: str | Path, topic: str = TOPICS['graph_fused']) -> list[int]:
    """Indices of the frames the node graph published ``topic`` for (the graph's keyframes)."""
    return sorted(match_stamps(sequence.stamps, list(recorded_depths(bag, topic))))


def recorded_bag(recorded: dict, what: str) -> str:
    """The recorded bag of ``--set recorded.bag=PATH`` (the ``recorded`` stage parameters),
    or a ``ValueError`` saying that ``what`` (a method, an option) needs it."""
    bag = recorded.get('bag')
    if not bag:
        raise ValueError(f'{what} needs the recorded bag: --set recorded.bag=PATH')
    return str(bag)


def _recorded(ctx: KeyframeContext, method: str) -> MethodOutput:
    bag = recorded_bag(ctx.stage_params('recorded'), method)
    topic = ctx.stage_params('recorded').get(method, TOPICS[method])
    table = ctx.shared_cached(
        f'recorded:{topic}',
        lambda: (depths := recorded_depths(bag, topic), match_stamps(ctx.sequence.stamps, list(depths))),
    )
    depths, by_frame = table
    ns = by_frame.get(ctx.index)
    if ns is None:  # the graph published nothing for this frame: it counts as no estimate
        return MethodOutput(
            np.full((ctx.camera.height, ctx.camera.width), np.nan, np.float32), {'published': 0.0}
        )
    return MethodOutput(depths[ns].astype(np.float32), {'published': 1.0})


@register_method('graph_fused', 'fused depth published by the ROS node graph (from --set recorded.bag=...)')
def graph_fused(ctx: KeyframeContext) -> MethodOutput:
    return _recorded(ctx, 'graph_fused')


@register_method('graph_single_view', 'single-view depth published by the ROS node graph (recorded bag)')
def graph_single_view(ctx: KeyframeContext) -> MethodOutput:
    return _recorded(ctx, 'graph_single_view')


@register_method(
    'graph_multi_view',
    'semi-dense multi-view depth published by the ROS node graph (recorded bag)',
    sparse=True,
)
def graph_multi_view(ctx: KeyframeContext) -> MethodOutput:
    return _recorded(ctx, 'graph_multi_view')
