"""The sweep's native coarse scores (``multiview/sweep_scores.c``) against the torch code.

Each row's lowest cost, its first index and the second-best ratio must be the torch code's
(``semidense._coarse_scores_torch`` of the volume with the unseen samples at inf) bit for bit:
with unseen samples, rows seen nowhere, ties, NaN costs and counts, one sample and many, split
over threads (the sweep with and without every native kernel: test_native_matching_cost.py).
"""

from __future__ import annotations

import math

import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.multiview import native_scores, semidense

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _native_or_skip() -> None:
    if native_scores._library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')


def _volume(rows: int, samples: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    cost = torch.rand(rows, samples, generator=gen) * 2.0
    cost[cost < 0.04] = math.inf  # a neighbour behind the camera
    cost[::97, 3 % samples] = math.nan  # degenerate rays
    cost[::50] = math.inf  # seen nowhere
    cost[1::50] = 0.5  # every sample tied
    count = torch.rand(rows, samples, generator=gen) * 4.0
    count[::31] = math.nan
    return cost, count


def _same(mine: torch.Tensor, theirs: torch.Tensor) -> bool:
    if not mine.dtype.is_floating_point:
        return torch.equal(mine, theirs)
    return torch.equal(mine.isnan(), theirs.isnan()) and torch.equal(
        mine.nan_to_num(nan=-7.0), theirs.nan_to_num(nan=-7.0)
    )


@pytest.mark.parametrize(
    ('rows', 'samples', 'exclusion'), [(1, 1, 2), (5, 3, 1), (1000, 64, 2), (4001, 48, 0)]
)
def test_the_native_scores_are_the_torch_scores(rows, samples, exclusion):
    _native_or_skip()
    cost, count = _volume(rows, samples, seed=rows)
    need = 1.5
    mine = native_scores.native_coarse_scores(cost, count, need, exclusion)
    assert mine is not None
    theirs = semidense._coarse_scores_torch(torch.where(count >= need, cost, math.inf), exclusion)
    for name, a, b in zip(('c1', 'best', 'distinct'), mine, theirs, strict=True):
        assert _same(a, b), name
    assert bool(torch.isfinite(theirs[0]).any()) or rows < 10


def test_rows_split_over_threads_give_the_same_scores(monkeypatch):
    _native_or_skip()
    cost, count = _volume(5003, 64, seed=2)
    one = native_scores.native_coarse_scores(cost, count, 1.5, 2)
    monkeypatch.setattr(native_scores, 'THREAD_MIN_ROWS', 1)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        split = native_scores.native_coarse_scores(cost, count, 1.5, 2)
    finally:
        torch.set_num_threads(before)
    assert all(_same(a, b) for a, b in zip(one, split, strict=True))


def test_the_kernel_declines_what_it_was_not_written_for():
    cost, count = _volume(20, 8, seed=3)
    assert native_scores.native_coarse_scores(cost.double(), count.double(), 1.5, 2) is None
    assert native_scores.native_coarse_scores(cost, count[:, :4], 1.5, 2) is None
