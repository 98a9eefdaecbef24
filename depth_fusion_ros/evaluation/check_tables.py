"""The report's tables of the calibration checks: time offset, mount, focal length.

One row per sequence that ran the check (``evaluation/checks.py``), its verdict and its fit,
so that a correction every method ran with is said in the report, not only in results.json.
A fit that means nothing (a flat time offset fit) is said as such, never as a number to copy.
"""

from __future__ import annotations

from typing import Any

from .markdown import table


def _check_table(doc: dict[str, Any], key: str, header: list[str], cells: Any) -> str | None:
    """A calibration check's table (``evaluation/checks.py``): one row per sequence that ran it,
    ``[name, verdict, *cells(entry)]``, so a correction is said in the report, not only in
    results.json."""
    rows = [
        [name, seq[key]['verdict'], *cells(seq[key])]
        for name, seq in doc['sequences'].items()
        if seq.get(key)
    ]
    return table(['sequence', 'verdict', *header], rows) if rows else None


def focal_table(doc: dict[str, Any]) -> str | None:
    """The focal length check per sequence (``evaluation/focal.py``)."""

    def cells(c: dict) -> list[str]:
        fit = f'{c["fitted_fx"]:.1f} ({c["scale"] - 1:+.1%} +- {c["stderr"]:.1%})'
        used = c['fitted_fx'] if c['corrected'] else c['told_fx']
        lens = c.get('lens_corrected_k1', 0.0)
        lens_used = f'{lens:+.3f}' if lens else 'none'
        return [f'{c["told_fx"]:.1f}', fit, str(c['pairs']), f'{used:.1f}', lens_used]

    header = ['told fx (px)', 'fitted fx (px)', 'pairs', 'fx every method used', 'lens k1 every method used']
    return _check_table(doc, 'focal_check', header, cells)


def time_offset_table(doc: dict[str, Any]) -> str | None:
    """The time offset check per sequence (``evaluation/time_offset.py``)."""

    def cells(c: dict) -> list[str]:
        used = c['fitted_offset'] if c['corrected'] else c['told']
        # A flat fit is noise, not an offset to copy (TimeOffsetEstimate.flat)
        if c.get('flat'):
            fit = 'flat (every offset fits alike)'
        else:
            fit = f'{c["offset"] * 1000:+.0f} +- {c["stderr"] * 1000:.0f}'
        return [fit, str(c['pairs']), f'{used * 1000:+.0f}']

    header = ['fitted offset (ms)', 'pairs', 'offset every method used (ms)']
    return _check_table(doc, 'time_offset_check', header, cells)


def mount_table(doc: dict[str, Any]) -> str | None:
    """The mount check per sequence (``evaluation/mount.py``)."""

    def cells(c: dict) -> list[str]:
        fit = ', '.join(f'{v:+.2f}' for v in c['fitted_deg'])
        sd = '/'.join(f'{v:.2f}' for v in c['stderr_deg'])
        used = f'{c["angle_deg"]:.2f}' if c['corrected'] else '0'
        return [f'[{fit}]', sd, str(c['observed']), str(c['pairs']), used]

    header = [
        'fitted rotation (deg)',
        'standard errors (deg)',
        'directions observed',
        'pairs',
        'turn every method used (deg)',
    ]
    return _check_table(doc, 'mount_check', header, cells)
