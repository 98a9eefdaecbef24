"""The guard's part of the evaluation report: decisions per sequence and per keyframe.

* :func:`decision_table` — for each sequence, how many keyframes took each step of the ladder
  (``fusion.guard.DECISIONS``), how many of them were withheld (no depth: a relative source
  without a trusted alignment, scored on no pixel), the mean keyframe confidence, and the MAE
  of the single-view depth, of ``fused`` and (when it ran) of ``fused_unguarded``;
* :func:`decision_figure` — ``guard_decisions.png``: per keyframe, the points the fusion used
  and the decision taken, against the keyframe index (time), one panel per sequence.

Both read the ``fused`` method's per-frame extras ``decision`` and ``n_omega``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..fusion.guard import DECISIONS
from .markdown import fmt, table

if TYPE_CHECKING:
    from .harness import SequenceResult

METHOD = 'fused'


def decision_table(doc: dict[str, Any]) -> str | None:
    """Markdown table of the guard's decisions per sequence (None when ``fused`` did not run)."""
    header = ['sequence', *DECISIONS, 'withheld', 'kf confidence', 'MAE single', 'MAE fused', 'MAE unguarded']
    rows = []
    for name, seq in doc['sequences'].items():
        methods = seq['methods']
        fused = methods.get(METHOD)
        if not fused or 'per_frame_extras' not in fused:
            continue
        levels = [int(v) for v in fused['per_frame_extras'].get('decision', [])]
        counts = [str(levels.count(i)) for i in range(len(DECISIONS))]
        single = next((methods[m] for m in ('single_view', 'single_view_simulated') if m in methods), {})
        rows.append(
            [
                name,
                *counts,
                str(int(sum(fused['per_frame_extras'].get('withheld', [])))),
                fmt(fused.get('keyframe_confidence')),
                fmt(single.get('mae')),
                fmt(fused.get('mae')),
                fmt(methods.get('fused_unguarded', {}).get('mae')),
            ]
        )
    if not rows:
        return None
    return table(header, rows)


def decision_figure(results: list[SequenceResult], path: Path) -> Path | None:
    """Per keyframe: points used (bars, left axis) and decision (steps, right axis)."""
    panels = [r for r in results if METHOD in r.records and r.records[METHOD].extras.get('decision')]
    if not panels:
        return None
    from .figures import _pyplot

    plt = _pyplot()
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.4 * len(panels)), squeeze=False)
    for ax, r in zip(axes[:, 0], panels, strict=True):
        extras = r.records[METHOD].extras
        x = np.asarray(r.keyframes[: len(extras['decision'])])
        ax.bar(
            x,
            extras['n_omega'],
            width=max(1.0, 0.8 * float(np.median(np.diff(x))) if len(x) > 1 else 1.0),
            color='tab:blue',
            alpha=0.5,
            label='points used',
        )
        ax.set_ylabel('points used')
        ax.set_title(r.name, fontsize=9)
        right = ax.twinx()
        right.step(x, extras['decision'], where='mid', color='tab:red', label='decision')
        right.set_yticks(range(len(DECISIONS)), DECISIONS, fontsize=7)
        right.set_ylim(-0.5, len(DECISIONS) - 0.5)
        right.invert_yaxis()
    axes[-1, 0].set_xlabel('keyframe (frame index)')
    fig.suptitle('guard: points used and alignment mode per keyframe', fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
