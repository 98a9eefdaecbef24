"""The run's one-line summary: every keyframe the policy chose, and what became of it.

Counted from the nodes' keyframe events (:mod:`depth_fusion_ros.nodes.graph_events`), so
keyframes the multi-view node dropped before announcing them are counted too, in both modes.
"""

from __future__ import annotations

from collections import Counter

from ..graph_events import LedgerSnapshot
from .options import RunResult


def drop_reasons(result: RunResult) -> dict[str, int]:
    """``{'multi_view.worker_queue_full': 9, ...}`` over the chosen keyframes; lost ones without
    a drop event count as ``unaccounted``."""
    fused = set(result.fused)
    reasons: Counter[str] = Counter()
    for stamp in result.chosen:
        if stamp in fused:
            continue
        reasons[result.drops.get(stamp, 'unaccounted')] += 1
    return dict(reasons)


def counts_line(chosen: int, fused: int, reasons: dict[str, int]) -> str:
    """``30 keyframes chosen, 21 fused, 9 dropped (multi_view.worker_queue_full=9)``."""
    detail = ' (' + ', '.join(f'{k}={v}' for k, v in sorted(reasons.items())) + ')' if reasons else ''
    return f'{chosen} keyframes chosen, {fused} fused, {sum(reasons.values())} dropped{detail}'


def fused_chosen(result: RunResult) -> int:
    """The chosen keyframes that were fused (a stray fused output of no chosen one not counted)."""
    return len(set(result.fused) & set(result.chosen))


def keyframe_summary(result: RunResult, mode: str) -> str:
    """``30 keyframes chosen, 21 fused, 9 dropped (multi_view.worker_queue_full=9) in 12.3 s
    (processes, real time)``."""
    pacing = 'paced' if result.paced else 'real time'
    counts = counts_line(len(result.chosen), fused_chosen(result), drop_reasons(result))
    line = f'{counts} in {result.seconds:.1f} s ({mode}, {pacing})'
    played = result.images_played
    if played is not None and result.images_handled < played:
        # Images that never reached the keyframe policy cannot be counted as keyframes: say so.
        line += f'; only {result.images_handled} of {played} images reached multi_view_node'
    return line


def empty_run(result: RunResult) -> str | None:
    """Why a run that ended by itself produced no fused depth, or ``None`` when it did: the
    reason ``depth-fusion run`` gives when it exits 1 instead of 0 on an empty result."""
    if fused_chosen(result):
        return None
    if not result.chosen:
        return (
            f'no keyframe was chosen from the {result.images_handled} images multi_view_node handled '
            '(too few posed frames, or too little motion between them): nothing was fused'
        )
    return f'none of the {len(result.chosen)} keyframes chosen was fused (see the drops above)'


def live_summary(snapshot: LedgerSnapshot, seconds: float) -> str:
    """``depth-fusion launch``'s closing count, from the keyframe events it heard: keyframes
    the policy chose and neither fused nor dropped by the stop (still in a node's hands, or
    their events lost) are ``in_flight``; then the images multi_view_node handled (posed or
    dropped), or that none came."""
    chosen = set(snapshot.chosen)
    reasons = dict(snapshot.drop_reasons())
    in_flight = len(snapshot.in_flight)
    if in_flight:
        reasons['in_flight_at_stop'] = in_flight
    fused = len(set(snapshot.fused) & chosen)
    line = f'{counts_line(len(chosen), fused, reasons)} in {seconds:.1f} s (live)'
    # What came in, so "0 keyframes" says whether the camera was heard at all.
    if snapshot.images:
        return f'{line}; {snapshot.images} images reached multi_view_node'
    return f'{line}; no image reached multi_view_node (check --image and that the camera publishes)'


def live_empty(snapshot: LedgerSnapshot) -> str | None:
    """Why a launch that was stopped fused nothing, or ``None`` when it fused something: the
    reason ``depth-fusion launch`` gives when it exits 1 instead of 0 (a clean stop of a graph
    that never produced a depth is not a success a script should go on from)."""
    chosen = set(snapshot.chosen)
    if set(snapshot.fused) & chosen:
        return None
    if not snapshot.images:
        return 'nothing was fused: no image reached multi_view_node'
    if not chosen:
        return (
            f'nothing was fused: no keyframe was chosen from the {snapshot.images} images multi_view_node '
            'handled (no poses, too few posed frames, or too little motion between them)'
        )
    return f'nothing was fused: none of the {len(chosen)} keyframes chosen (see the drops above)'
