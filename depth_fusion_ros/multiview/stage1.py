"""Stage 1 of the point selection, per multi-view method: which estimates reach RANSAC.

The paper's stage 1 (§III-D) keeps the best ``fraction`` of the sweep's estimates by score:
a sweep publishes the cost minimum of *every* candidate pixel, and most of the wrong ones are
poorly scored. The temporal filter publishes only pixels that already passed its own test
(enough measurements, inlier ratio and relative std within the ``filter.*`` thresholds). A
second cut by score then throws away converged estimates, and because any ranking of them
follows how long a region has been tracked, the survivors pack into part of the image and
the fusion extrapolates from there. Measured on the synthetic room (10 keyframes, simulated
prior, docs/fusion.md): fused MAE 0.392 m with the best 25 %, 0.362 m with all of them,
against 0.371 m for the sweep at its 25 %. So the filter's rule is ``all``: every published
estimate goes to stage 2, whose RANSAC still removes the ones that disagree with the
single-view depth.

Rules: ``fraction`` (the paper's best fraction by score), ``all`` (every estimate) and
``auto`` (the rule of the method that produced the estimate, :data:`METHOD_RULES`).
"""

from __future__ import annotations

import numpy as np

STAGE1_RULES = ('auto', 'fraction', 'all')
#: The stage-1 rule each multi-view method's output calls for.
METHOD_RULES = {'sweep': 'fraction', 'filter': 'all'}


def resolve_rule(rule: str, method: str | None) -> str:
    """``fraction`` or ``all``: ``rule`` itself, or for ``auto`` the rule of ``method``
    (``fraction``, the paper's, when the method is unknown: nothing announced yet)."""
    if rule not in STAGE1_RULES:
        raise ValueError(f'stage1 must be one of {", ".join(STAGE1_RULES)}, got {rule!r}')
    if rule != 'auto':
        return rule
    return METHOD_RULES.get(method or '', 'fraction')


def stage1_mask(depth: np.ndarray, score: np.ndarray, rule: str, fraction: float) -> np.ndarray:
    """Bool mask of the stage-1 points under a resolved rule (``fraction`` or ``all``)."""
    if rule == 'all':
        return np.isfinite(depth) & (depth > 0)
    if rule != 'fraction':
        raise ValueError(f'stage1 rule must be resolved to fraction or all, got {rule!r}')
    return best_fraction_mask(depth, score, fraction)


def best_fraction_mask(depth: np.ndarray, score: np.ndarray, fraction: float = 0.25) -> np.ndarray:
    """The paper's rule on the two maps it reads (``semidense.select_best_fraction`` of a result)."""
    if not (0 < fraction <= 1):
        raise ValueError(f'select_fraction must be in (0, 1], got {fraction}')
    valid = np.isfinite(depth) & np.isfinite(score)
    count = int(valid.sum())
    mask = np.zeros(depth.shape, dtype=bool)
    if count == 0:
        return mask
    keep = max(1, round(fraction * count))
    flat = np.flatnonzero(valid)
    scores = score.ravel()[flat]
    best = flat[np.argpartition(-scores, keep - 1)[:keep]] if keep < count else flat
    mask.ravel()[best] = True
    return mask
