"""The guard: multi-view points held out of training decide whether an update is kept.

Before a keyframe's update the guard scores the network on the held-out points of that
keyframe and of the most recent keyframes in the replay buffer (mean over keyframes of the
mean ``|log z_pred - log z_mv|``); after it, on the same points. The recent keyframes matter:
a keyframe whose multi-view depth is wrong everywhere (a bad pose, a poisoned input) fits its
own held-out points better and better, while the other keyframes' points reveal the damage.

An update is rolled back when it makes that error worse by more than ``tolerance`` (relative)
*and the held-out points show it*: the before/after comparison is paired (the same points,
the same targets), so its noise is the spread of the per-point changes, not of the errors.
With ``D`` the change of the guard error and ``SE`` its standard error (per keyframe, the
variance of the per-point changes over the number of points; averaged like the error), the
update is rolled back when ``D > tolerance * before + z * SE`` (a one-sided test that the
worsening exceeds the tolerance; ``z = 0`` is the plain threshold ``after > before * (1 +
tolerance)``). Why: the held-out multi-view depths are themselves ~4-6 % noisy, and an
update that moves the error by a fraction of a per cent on a few hundred points per keyframe
is within what a different draw of points would show; a poisoned update moves it by many
standard errors.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from .batch import point_batch
from .losses import sparse_point_errors
from .prepared import PreparedSample


@dataclass
class GuardVerdict:
    before: float
    after: float
    rolled_back: bool
    #: Keyframes whose held-out points were checked.
    keyframes: int
    #: Standard error of ``after - before`` from the paired per-point changes (NaN: not judged).
    se: float = float('nan')


@torch.no_grad()
def guard_point_errors(
    forward: Callable[[torch.Tensor], torch.Tensor], samples: Sequence[PreparedSample]
) -> list[torch.Tensor]:
    """Per sample (all must have held-out points), the (n_holdout,) ``|log z_pred - log z_mv|``
    at its held-out points, in one forward pass; left on the device (no host sync)."""
    log_depth = forward(torch.cat([s.x for s in samples]))
    points = point_batch([s.holdout_grid for s in samples], [s.holdout_log for s in samples])
    error = sparse_point_errors(log_depth, points.grid, points.target)
    return [error[b, : s.n_holdout] for b, s in enumerate(samples)]


def guard_error(forward: Callable[[torch.Tensor], torch.Tensor], samples: Sequence[PreparedSample]) -> float:
    """Mean over ``samples`` (with held-out points) of their mean held-out log-depth error;
    NaN when no sample has held-out points."""
    usable = [s for s in samples if s.n_holdout > 0]
    if not usable:
        return float('nan')
    return float(torch.stack([e.mean() for e in guard_point_errors(forward, usable)]).mean())


def paired_change(
    before: Sequence[torch.Tensor], after: Sequence[torch.Tensor]
) -> tuple[float, float, float, float]:
    """``(before, after, change, se)`` of the guard error for per-keyframe point errors
    measured with the old and the new weights at the same points (one host read)."""
    if len(before) != len(after) or not before:
        raise ValueError(f'paired guard errors need the same keyframes, got {len(before)} and {len(after)}')
    rows = []
    for b, a in zip(before, after, strict=True):
        if b.shape != a.shape:
            raise ValueError(
                f'paired guard errors need the same points, got {tuple(b.shape)} and {tuple(a.shape)}'
            )
        d = a - b
        var = d.var(unbiased=True) if d.numel() > 1 else d.new_zeros(())
        rows.append(torch.stack([b.mean(), a.mean(), var / d.numel()]))
    b_mean, a_mean, var_sum = (float(v) for v in torch.stack(rows).sum(dim=0).tolist())
    k = len(rows)
    return b_mean / k, a_mean / k, (a_mean - b_mean) / k, math.sqrt(max(var_sum, 0.0)) / k


def judge(
    before: Sequence[torch.Tensor], after: Sequence[torch.Tensor], tolerance: float, z: float = 0.0
) -> GuardVerdict:
    """Roll back when the paired worsening exceeds ``tolerance * before`` by more than ``z``
    standard errors, or the error is not finite. No keyframe with held-out points: nothing to
    judge by, kept."""
    if not before:
        return GuardVerdict(float('nan'), float('nan'), False, 0)
    b, a, change, se = paired_change(before, after)
    if not (math.isfinite(b) and math.isfinite(a) and math.isfinite(se)):
        return GuardVerdict(b, a, True, len(before), se)
    return GuardVerdict(b, a, change > tolerance * b + z * se, len(before), se)
