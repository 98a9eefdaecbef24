"""The guard: multi-view points held out of training decide whether an update is kept.

Before a keyframe's update the guard scores the network on the held-out points of that
keyframe and of the most recent keyframes in the replay buffer (mean over keyframes of the
mean ``|log z_pred - log z_mv|``); after it, on the same points. An update that makes this
worse by more than ``tolerance`` is rolled back. The recent keyframes matter: a keyframe
whose multi-view depth is wrong everywhere (a bad pose, a poisoned input) fits its own
held-out points better and better, while the other keyframes' points reveal the damage.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from .batch import point_batch
from .losses import sparse_batch
from .prepared import PreparedSample


@dataclass
class GuardVerdict:
    before: float
    after: float
    rolled_back: bool
    #: Keyframes whose held-out points were checked.
    keyframes: int


@torch.no_grad()
def guard_errors(
    forward: Callable[[torch.Tensor], torch.Tensor], samples: Sequence[PreparedSample]
) -> torch.Tensor:
    """(len(samples),) mean held-out log-depth error of each sample (all must have held-out
    points), in one forward pass; left on the device (no host sync)."""
    log_depth = forward(torch.cat([s.x for s in samples]))
    points = point_batch([s.holdout_grid for s in samples], [s.holdout_log for s in samples])
    return sparse_batch(log_depth, points.grid, points.target, points.mask)


def guard_error(forward: Callable[[torch.Tensor], torch.Tensor], samples: Sequence[PreparedSample]) -> float:
    """Mean over ``samples`` (with held-out points) of their mean held-out log-depth error;
    NaN when no sample has held-out points."""
    usable = [s for s in samples if s.n_holdout > 0]
    if not usable:
        return float('nan')
    return float(guard_errors(forward, usable).mean())


def judge(before: float, after: float, tolerance: float, keyframes: int) -> GuardVerdict:
    """Roll back when ``after > before * (1 + tolerance)`` (or the error is not finite)."""
    if math.isnan(before):  # NaN: nothing held out, nothing to judge by
        return GuardVerdict(before, after, False, 0)
    worse = math.isnan(after) or after > before * (1.0 + tolerance)
    return GuardVerdict(before, after, worse, keyframes)
