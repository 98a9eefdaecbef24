"""Report parts of online adaptation: MAE against keyframes seen (figure) and the ratio table.

Adapted methods are scored prequentially, so the per-frame MAE in the order of the keyframes
*is* the learning curve: keyframe k was predicted by the network after k keyframes of
adaptation. The figure draws it for the adapted methods next to their frozen counterparts
(thin: per keyframe; thick: running mean); the table gives adapted / frozen MAE ratios and
the guard's rollbacks.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .harness import SequenceResult

#: (frozen method, adapted method) pairs.
PAIRS = (('single_view', 'single_view_adapted'), ('fused', 'fused_adapted'))
COLOURS = {
    'single_view': 'tab:blue',
    'single_view_adapted': 'tab:orange',
    'fused': 'tab:green',
    'fused_adapted': 'tab:red',
}


def _has_adapted(result: SequenceResult) -> bool:
    return any(a in result.records for _, a in PAIRS)


def adaptation_curves(results: list[SequenceResult], path: Path) -> Path | None:
    """Per-sequence panels: MAE of each keyframe against keyframes seen, and its running mean."""
    panels = [r for r in results if _has_adapted(r)]
    if not panels:
        return None
    from .figures import _pyplot

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.0 * len(panels), 3.6), squeeze=False)
    for ax, r in zip(axes[0], panels, strict=True):
        for frozen, adapted in PAIRS:
            for name in (frozen, adapted):
                if name not in r.records:
                    continue
                mae = np.array(r.records[name].all.mae_per_frame, dtype=float)
                seen = np.arange(len(mae))
                ax.plot(seen, mae, color=COLOURS[name], alpha=0.35, lw=0.8)
                running = np.nancumsum(mae) / np.maximum(1, np.cumsum(np.isfinite(mae)))
                ax.plot(seen, running, color=COLOURS[name], lw=2, label=f'{name} (running mean)')
        ax.set_xlabel('keyframes seen before this one (prequential)')
        ax.set_ylabel('MAE (m)')
        ax.set_title(r.name, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def adaptation_table(doc: dict[str, Any]) -> str | None:
    """Adapted vs frozen MAE per sequence, their ratio, and the guard's rollbacks."""
    rows = []
    for name, s in doc['sequences'].items():
        ms = s['methods']
        for frozen, adapted in PAIRS:
            if adapted not in ms:
                continue
            a = ms[adapted].get('mae')
            f = ms.get(frozen, {}).get('mae')
            ratio = a / f if a is not None and f else None
            rollbacks = ms[adapted].get('adapt_rolled_back')
            frames = s.get('frames', 0)
            rows.append(
                '| '
                + ' | '.join(
                    [
                        name,
                        adapted,
                        '–' if f is None else f'{f:.3f}',
                        '–' if a is None else f'{a:.3f}',
                        '–' if ratio is None else f'{ratio:.2f}',
                        '–' if rollbacks is None else f'{round(rollbacks * frames)}',
                    ]
                )
                + ' |'
            )
    if not rows:
        return None
    header = (
        '| sequence | method | MAE frozen (m) | MAE adapted (m) | ratio | rollbacks |\n'
        '|---|---|---:|---:|---:|---:|'
    )
    return header + '\n' + '\n'.join(rows)
