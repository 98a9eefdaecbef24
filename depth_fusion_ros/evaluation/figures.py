"""PNG figures of an evaluation run, in the spirit of the paper's Figs. 2, 5, 6 and 7.

* ``<seq>_depths.png`` — sample keyframes: RGB, each method's depth, ground truth, one
  colour scale per row (Fig. 6);
* ``<seq>_errors.png`` — absolute error images of single-view and fused depth (Fig. 5);
* ``error_boxplots.png`` — per-sequence error distributions per method (Fig. 7);
* ``single_view_error_histogram.png`` — signed single-view error per sequence (Fig. 2);
* ``guard_decisions.png`` — the guard's decision and points used per keyframe (``guard_report``).

matplotlib runs headless (Agg); nothing here is needed to compute the numbers.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .harness import SequenceResult

#: Column order of the depth grid (the paper's Fig. 6), then anything else that ran.
DEPTH_COLUMNS = (
    'tv',
    'multi_view',
    'single_view',
    'single_view_simulated',
    'fused',
    'fused_oracle',
    'graph_fused',
)
ERROR_COLUMNS = ('single_view', 'single_view_simulated', 'fused', 'fused_oracle', 'graph_fused')
BOX_ORDER = (
    'fused_oracle',
    'fused',
    'graph_fused',
    'single_view',
    'single_view_simulated',
    'multi_view',
    'tv',
)
DEPTH_CMAP = 'turbo'
ERROR_CMAP = 'magma'


def _pyplot():
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def _columns(result: SequenceResult, preferred: tuple[str, ...]) -> list[str]:
    return [m for m in preferred if m in result.records and result.records[m].samples]


def _show(ax, image: np.ndarray, title: str, **kw) -> object:
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=8)
    if image.ndim == 2:
        image = np.ma.masked_invalid(image)
    return ax.imshow(image, interpolation='nearest', **kw)


def _row_range(gt: np.ndarray) -> tuple[float, float]:
    valid = gt[np.isfinite(gt) & (gt > 0)]
    if valid.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(valid, [2, 98])
    return float(lo), float(max(hi, lo + 1e-3))


def depth_grid(result: SequenceResult, path: Path) -> Path | None:
    """Sample keyframes x (RGB, methods..., ground truth), one depth colour scale per row."""
    cols = _columns(result, DEPTH_COLUMNS)
    frames = sorted(next((r.samples for r in result.records.values() if r.samples), {}))
    if not frames:
        return None
    plt = _pyplot()
    ncols = len(cols) + 2
    fig, axes = plt.subplots(len(frames), ncols, figsize=(2.2 * ncols, 1.8 * len(frames)), squeeze=False)
    cmap = plt.get_cmap(DEPTH_CMAP).with_extremes(bad='black')
    for r, i in enumerate(frames):
        gt = result.sequence.gt_depth_working(i)
        lo, hi = _row_range(gt)
        _show(axes[r, 0], result.sequence.frames[i].rgb, f'frame {i}')
        for c, m in enumerate(cols, start=1):
            _show(axes[r, c], result.records[m].samples[i], m, cmap=cmap, vmin=lo, vmax=hi)
        im = _show(axes[r, -1], gt, 'ground truth', cmap=cmap, vmin=lo, vmax=hi)
        fig.colorbar(im, ax=axes[r, -1], fraction=0.046, pad=0.02, label='m')
    fig.suptitle(f'{result.name}: depth (black = no estimate)', fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def error_grid(result: SequenceResult, path: Path) -> Path | None:
    """Absolute error images |prediction - ground truth| with one colour scale per row."""
    cols = _columns(result, ERROR_COLUMNS)
    if not cols:
        return None
    frames = sorted(result.records[cols[0]].samples)
    plt = _pyplot()
    ncols = len(cols) + 1
    fig, axes = plt.subplots(len(frames), ncols, figsize=(2.3 * ncols, 1.8 * len(frames)), squeeze=False)
    cmap = plt.get_cmap(ERROR_CMAP).with_extremes(bad='dimgray')
    for r, i in enumerate(frames):
        gt = result.sequence.gt_depth_working(i)
        errors = {m: np.abs(result.records[m].samples[i] - gt) for m in cols}
        finite = np.concatenate([e[np.isfinite(e)] for e in errors.values()])
        vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
        _show(axes[r, 0], result.sequence.frames[i].rgb, f'frame {i}')
        im = None
        for c, m in enumerate(cols, start=1):
            mae = np.nanmean(errors[m]) if np.isfinite(errors[m]).any() else np.nan
            im = _show(axes[r, c], errors[m], f'{m} (MAE {mae:.2f} m)', cmap=cmap, vmin=0, vmax=vmax)
        fig.colorbar(im, ax=axes[r, -1], fraction=0.046, pad=0.02, label='|error| m')
    fig.suptitle(
        f'{result.name}: absolute depth error (darker is better, grey = no ground truth)', fontsize=10
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def error_boxplots(results: list[SequenceResult], path: Path) -> Path | None:
    """Per-sequence box-and-whisker plots of the absolute pixel error of each method."""
    panels = [(r, [m for m in BOX_ORDER if m in r.records and r.records[m].all.n]) for r in results]
    panels = [(r, ms) for r, ms in panels if ms]
    if not panels:
        return None
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.6), squeeze=False)
    for ax, (r, methods) in zip(axes[0], panels, strict=True):
        data = [r.records[m].all.errors() for m in methods]
        ax.boxplot(data, showfliers=False, whis=(5, 95))
        ax.set_xticks(range(1, len(methods) + 1), methods, rotation=30, ha='right', fontsize=8)
        ax.set_ylabel('|error| (m), whiskers 5-95 %')
        ax.set_title(r.name, fontsize=9)
        ax.grid(axis='y', alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def single_view_histogram(results: list[SequenceResult], path: Path) -> Path | None:
    """Histogram of the signed single-view error (prediction - ground truth) per sequence."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    drawn = False
    for r in results:
        for m in ('single_view', 'single_view_simulated'):
            if m in r.records and r.records[m].all.n:
                err = r.records[m].all.signed_errors()
                lim = float(np.percentile(np.abs(err), 99)) or 1.0
                ax.hist(
                    err, bins=120, range=(-lim, lim), histtype='step', density=True, label=f'{r.name} ({m})'
                )
                drawn = True
                break
    if not drawn:
        plt.close(fig)
        return None
    ax.set_xlabel('single-view error: prediction - ground truth (m)')
    ax.set_ylabel('density')
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def sequence_figures(result: SequenceResult, out_dir: Path) -> list[Path]:
    """Pictures of sequence-level methods (e.g. the maps); a figure shared by several methods
    is drawn once."""
    drawn: list = []
    paths: list[Path] = []
    for record in result.records.values():
        figure = record.sequence_output.figure if record.sequence_output else None
        if figure is not None and not any(figure is f for f in drawn):
            drawn.append(figure)
            paths.extend(figure(out_dir))
    return paths


def write_figures(results: list[SequenceResult], out_dir: Path) -> list[Path]:
    """Every figure of the run; returns the files written."""
    written: list[Path | None] = []
    for r in results:
        written.append(depth_grid(r, out_dir / f'{r.name}_depths.png'))
        written.append(error_grid(r, out_dir / f'{r.name}_errors.png'))
        written.extend(sequence_figures(r, out_dir))
    written.append(error_boxplots(results, out_dir / 'error_boxplots.png'))
    written.append(single_view_histogram(results, out_dir / 'single_view_error_histogram.png'))
    from .guard_report import decision_figure

    written.append(decision_figure(results, out_dir / 'guard_decisions.png'))
    from .adaptation_report import adaptation_curves

    written.append(adaptation_curves(results, out_dir / 'adaptation_mae.png'))
    return [p for p in written if p is not None]
