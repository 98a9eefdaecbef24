"""``report.md`` in the paper's table layout, plus the figures of an evaluation run.

Tables (each appears when the methods it needs were run):

* paper Table II: RMSE, scale-invariant and mean error of TV / single-view / fused per
  sequence, with the oracle ("manual") selection's mean error;
* paper Table III: the weight ablation (W1, W1·W2, all four) on oracle points;
* paper Table I: median error on high- and low-gradient pixels;
* the calibration checks' verdicts (``check_tables.py``), the guard's decisions, the
  distance bands and the adaptation (each in its own module);
* every metric of every method, per sequence.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .adaptation_report import adaptation_table
from .check_tables import focal_table, mount_table, time_offset_table
from .distance_bands import band_table
from .guard_report import decision_table
from .markdown import fmt, table

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
    ('good_density', 'density AbsRel≤10 %', '{:.3f}'),
    ('n_omega', '|Ω|', '{:.0f}'),
    ('map_accuracy_median_m', 'map acc. median (m)', '{:.3f}'),
    ('map_accuracy_mean_m', 'map acc. mean (m)', '{:.3f}'),
    ('map_completeness_5cm', 'map compl. 5 cm', '{:.3f}'),
    ('map_completeness_10cm', 'map compl. 10 cm', '{:.3f}'),
    ('seconds_per_frame', 's/frame', '{:.3f}'),
]


def metrics_table(methods: dict[str, dict[str, Any]]) -> str:
    """One row per method, the metric columns any method reports."""
    cols = [c for c in COLUMNS if any(c[0] in m for m in methods.values())]
    rows = [[name] + [fmt(m.get(k), f) for k, _, f in cols] for name, m in methods.items()]
    return table(['method'] + [c[1] for c in cols], rows)


def _single_view_name(methods: dict[str, Any]) -> str | None:
    return next((m for m in ('single_view', 'single_view_simulated') if m in methods), None)


def paper_table(doc: dict[str, Any]) -> str | None:
    """Paper Table II: TV / single-view / fused for RMSE, SI and MAE, plus oracle MAE."""
    seqs = doc['sequences']
    if not any('fused' in s['methods'] or 'tv' in s['methods'] for s in seqs.values()):
        return None
    header = ['sequence']
    for metric in ('RMSE', 'scale-inv.', 'MAE (m)'):
        header += [f'{metric} TV', f'{metric} single', f'{metric} fused']
    header.append('MAE fused (oracle)')
    rows = []
    for name, s in seqs.items():
        ms = s['methods']
        sv = _single_view_name(ms)
        row = [name]
        for key in ('rmse', 'si', 'mae'):
            for method in ('tv', sv, 'fused'):
                row.append(fmt(ms.get(method, {}).get(key)) if method else '–')
        row.append(fmt(ms.get('fused_oracle', {}).get('mae')))
        rows.append(row)
    return table(header, rows)


def ablation_table(doc: dict[str, Any]) -> str | None:
    """Paper Table III: weights W1, W1·W2 and all four, all on oracle points."""
    names = ('fused_w1', 'fused_w1w2', 'fused_oracle')
    seqs = doc['sequences']
    if not any(all(n in s['methods'] for n in names) for s in seqs.values()):
        return None
    header = ['sequence', 'SI W1', 'SI W1·W2', 'SI all four', 'MAE W1', 'MAE W1·W2', 'MAE all four']
    rows, values = [], []
    for name, s in seqs.items():
        ms = s['methods']
        if not all(n in ms for n in names):
            continue
        v = [ms[n].get('si') for n in names] + [ms[n].get('mae') for n in names]
        values.append(v)
        rows.append([name] + [fmt(x) for x in v])
    if len(values) > 1:
        mean = np.nanmean(np.array(values, dtype=float), axis=0)
        rows.append(['**mean**'] + [fmt(float(x)) for x in mean])
    return table(header, rows)


def gradient_table(doc: dict[str, Any]) -> str | None:
    """Paper Table I: median absolute error (m) on high- and low-gradient pixels."""
    rows = []
    for name, s in doc['sequences'].items():
        for method in ('multi_view', 'single_view', 'single_view_simulated', 'tv', 'fused'):
            m = s['methods'].get(method)
            if m and 'gradient' in m:
                g = m['gradient']
                rows.append(
                    [
                        name,
                        method,
                        fmt(g['high'].get('median_abs_err')),
                        fmt(g['low'].get('median_abs_err')),
                    ]
                )
    if not rows:
        return None
    return table(['sequence', 'method', 'high-gradient', 'low-gradient'], rows)


def _keyframe_choice(opts: dict[str, Any]) -> str:
    if opts.get('recorded_keyframes'):
        return 'keyframes: those the recorded node graph fused'
    if opts.get('keyframes') is not None:
        return 'keyframes: a given list'
    return f'keyframe stride {opts.get("stride")}'


def coverage_notes(seq: dict[str, Any]) -> list[str]:
    """A line per recorded-graph method that has output for only some of the keyframes: its
    figures are over those alone, so beside the offline methods (scored on all) they compare
    different frames. Said, not left for the reader to find in results.json."""
    notes = []
    for name, m in seq['methods'].items():
        published = m.get('published')
        if published is None or published >= 1.0:
            continue
        n = len(seq.get('keyframes', []))
        notes.append(
            f'`{name}`: the graph published {round(published * n)} of these {n} keyframes; its figures '
            "are over those alone (`--recorded-keyframes` scores every method on the graph's keyframes)."
        )
    return notes


def report_markdown(doc: dict[str, Any], figures: list[str] | None = None) -> str:
    opts = doc.get('options', {})
    out = ['# depth_fusion_ros evaluation', '']
    out.append(
        f'Working resolution {opts.get("width")}x{opts.get("height")}, first {opts.get("frames")} frames, '
        f'{_keyframe_choice(opts)}, single-view source `{opts.get("single_view")}`, '
        f'{opts.get("num_neighbours")} neighbours ({opts.get("neighbour_mode")}), seed {opts.get("seed")}. '
        'Errors on valid ground-truth pixels after upsampling predictions to the ground-truth '
        'resolution; semi-dense methods are scored on the pixels they estimate.'
    )
    out.append('')
    sections = [
        ('Time offset check (docs/multi_view.md)', time_offset_table(doc)),
        ('Mount check (docs/multi_view.md)', mount_table(doc)),
        ('Focal length check (docs/multi_view.md)', focal_table(doc)),
        ('Main results (paper Table II layout)', paper_table(doc)),
        ('Weight ablation on oracle points (paper Table III)', ablation_table(doc)),
        ('Median error by image gradient (paper Table I, threshold 0.35)', gradient_table(doc)),
        ("The fusion's guard: decisions per sequence (keyframes)", decision_table(doc)),
        (
            'Where the fusion helps: fused / single-view MAE by distance to the nearest fused point '
            '(working grid; evaluation/distance_bands.py)',
            band_table(doc),
        ),
        ('Online adaptation, prequential (figure adaptation_mae.png)', adaptation_table(doc)),
    ]
    for title, section in sections:
        if section:
            out += [f'## {title}', '', section, '']
    out += ['## All metrics', '']
    for name, seq in doc['sequences'].items():
        out += [f'### {name} ({seq["frames"]} keyframes)', '', metrics_table(seq['methods']), '']
        notes = coverage_notes(seq)
        out += [*notes, ''] if notes else []
    if figures:
        out += ['## Figures', '']
        out += [f'![{Path(f).stem}]({Path(f).name})' for f in figures]
        out.append('')
    out += ['## Methods', '']
    out += [f'- `{k}`: {v}' for k, v in doc.get('methods', {}).items()]
    return '\n'.join(out) + '\n'


def write_report(
    doc: dict[str, Any], results: list[SequenceResult], out_dir: Path, figures: bool = True
) -> Path:
    written: list[str] = []
    if figures and results:
        from .figures import write_figures

        written = [str(p) for p in write_figures(results, out_dir)]
    path = out_dir / 'report.md'
    path.write_text(report_markdown(doc, written))
    return path
