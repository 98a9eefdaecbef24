"""Where the fusion helps: fused against single-view error by distance to the nearest fused point.

A point of Ω corrects the single-view depth around it; the interpolation's normalised
weights carry that correction to pixels far from every point, where the single-view error
may be another region's (docs/fusion.md, "Corrections that travel too far"). A keyframe's
MAE mixes both. So the ``fused`` method also records, per keyframe, the absolute errors of
the fused depth and of the single-view depth it started from, summed per band of distance
(px on the working grid) to the nearest point of Ω; the report sums them over the
keyframes of a sequence and prints fused / single per band. Evaluation only: it reads the
ground truth.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from .markdown import table

#: Band edges (px on the working grid): on the point, next to it, its neighbourhood, far.
BAND_EDGES = (0.0, 2.0, 6.0, 24.0, np.inf)
FIELDS = ('n', 'single', 'fused')


def band_names() -> list[str]:
    """``0-2``, ``2-6``, ``6-24``, ``24+``."""
    names = []
    for lo, hi in itertools.pairwise(BAND_EDGES):
        names.append(f'{lo:g}+' if not np.isfinite(hi) else f'{lo:g}-{hi:g}')
    return names


def _key(band: int, field: str) -> str:
    return f'band{band}_{field}'


def band_sums(single: np.ndarray, fused: np.ndarray, gt: np.ndarray, omega: np.ndarray) -> dict[str, float]:
    """Per band: pixels scored (``band<i>_n``) and the summed absolute errors of ``single`` and
    ``fused`` against ``gt`` (``band<i>_single``, ``band<i>_fused``), on the pixels where all
    three are finite and ``gt`` is positive. Empty Ω: every pixel is in the last band."""
    from scipy.ndimage import distance_transform_edt

    with np.errstate(invalid='ignore'):
        valid = np.isfinite(single) & np.isfinite(fused) & np.isfinite(gt) & (gt > 0)
        err_single, err_fused = np.abs(single - gt), np.abs(fused - gt)  # read on valid pixels only
    distance = distance_transform_edt(~omega) if omega.any() else np.full(omega.shape, np.inf)
    out: dict[str, float] = {}
    for i, (lo, hi) in enumerate(itertools.pairwise(BAND_EDGES)):
        sel = valid & (distance >= lo) & ((distance < hi) if np.isfinite(hi) else True)
        out[_key(i, 'n')] = float(sel.sum())
        out[_key(i, 'single')] = float(err_single[sel].sum())
        out[_key(i, 'fused')] = float(err_fused[sel].sum())
    return out


def band_table(doc: dict[str, Any], method: str = 'fused') -> str | None:
    """Markdown: per sequence and band, the share of the scored pixels and fused / single MAE
    (None when ``method`` did not record bands)."""
    names = band_names()
    header = ['sequence', *(f'{n} px: share, fused / single' for n in names)]
    rows = []
    for name, seq in doc['sequences'].items():
        extras = seq['methods'].get(method, {}).get('per_frame_extras', {})
        if _key(0, 'n') not in extras:
            continue
        sums = {
            k: float(np.nansum([v for v in extras.get(k, []) if v is not None]))
            for k in (_key(i, f) for i in range(len(names)) for f in FIELDS)
        }
        total = sum(sums[_key(i, 'n')] for i in range(len(names)))
        cells = []
        for i in range(len(names)):
            n, s, f = (sums[_key(i, x)] for x in FIELDS)
            if n == 0 or total == 0:
                cells.append('–')
            else:
                ratio = f'{f / s:.2f}' if s > 0 else '–'
                cells.append(f'{n / total:.0%}, {ratio}')
        rows.append([name, *cells])
    if not rows:
        return None
    return table(header, rows)
