"""``report.md`` (tables in the paper's layout) and figures from an evaluation run."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .harness import SequenceResult

COLUMNS = [
    ('mae', 'MAE (m)', '{:.3f}'),
    ('rmse', 'RMSE (m)', '{:.3f}'),
    ('si', 'scale-inv.', '{:.3f}'),
    ('abs_rel', 'AbsRel', '{:.3f}'),
    ('delta1', 'δ<1.25', '{:.3f}'),
    ('median_abs_rel', 'median AbsRel', '{:.3f}'),
    ('density', 'density', '{:.3f}'),
    ('seconds_per_frame', 's/frame', '{:.3f}'),
]


def _fmt(value: Any, pattern: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '–'
    return pattern.format(value)


def metrics_table(methods: dict[str, dict[str, Any]]) -> str:
    """Markdown table: one row per method, the metric columns any method reports."""
    cols = [c for c in COLUMNS if any(c[0] in m for m in methods.values())]
    lines = [
        '| method | ' + ' | '.join(c[1] for c in cols) + ' |',
        '|---|' + '---:|' * len(cols),
    ]
    for name, m in methods.items():
        lines.append(f'| {name} | ' + ' | '.join(_fmt(m.get(k), f) for k, _, f in cols) + ' |')
    return '\n'.join(lines)


def report_markdown(doc: dict[str, Any]) -> str:
    out = ['# depth_fusion_ros evaluation', '']
    opts = doc.get('options', {})
    out.append(
        f'Working resolution {opts.get("width")}x{opts.get("height")}, first {opts.get("frames")} frames, '
        f'stride {opts.get("stride")}, single-view source `{opts.get("single_view")}`, '
        f'neighbours {opts.get("num_neighbours")} ({opts.get("neighbour_mode")}), seed {opts.get("seed")}.'
    )
    out.append('Metrics on valid ground-truth pixels after upsampling to the ground-truth resolution.')
    out.append('')
    for name, seq in doc['sequences'].items():
        out += [f'## {name} ({seq["frames"]} keyframes)', '', metrics_table(seq['methods']), '']
    out += ['## Methods', '']
    out += [f'- `{k}`: {v}' for k, v in doc.get('methods', {}).items()]
    return '\n'.join(out) + '\n'


def write_report(
    doc: dict[str, Any], results: list[SequenceResult], out_dir: Path, figures: bool = True
) -> Path:
    path = out_dir / 'report.md'
    path.write_text(report_markdown(doc))
    return path
