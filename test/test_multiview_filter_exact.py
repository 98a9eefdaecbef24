"""The filter's CPU shortcuts give the same numbers as the plain forms they replace.

Each shortcut (numpy's index of a mask, bucket membership straight from the interval
tests, the update of only the rows that change, the scene depth's median by numpy's
selection) is checked against the plain torch form it replaced (for the update, the dense
form the GPU still runs), bit for bit, on random inputs that reach every branch: empty, all
and strided masks; buckets switched off; rows that match, fail, are new, and fall below the
inlier ratio.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from bucket_index import plan_buckets

from depth_fusion_ros.multiview.filter import _lower_median
from depth_fusion_ros.multiview.filter_buckets import bucket_members
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.filter_matches import Matches, _apply_dense, apply_matches
from depth_fusion_ros.multiview.filter_update import BetaGaussian
from depth_fusion_ros.true_indices import true_indices


def _nonzero(mask: torch.Tensor) -> torch.Tensor:
    return torch.nonzero(mask, as_tuple=True)[0]


@pytest.mark.parametrize('n', [0, 1, 7, 25_000])
def test_true_indices_are_torch_nonzeros(n):
    gen = torch.Generator().manual_seed(n)
    for mask in (
        torch.rand(n, generator=gen) > 0.5,
        torch.zeros(n, dtype=torch.bool),
        torch.ones(n, dtype=torch.bool),
        (torch.rand(2 * n, generator=gen) > 0.3)[::2],  # a strided view
    ):
        got = true_indices(mask)
        assert got.dtype == torch.long
        assert torch.equal(got, _nonzero(mask))


def _where_chain(span: torch.Tensor, fresh: torch.Tensor, c: FilterConfig) -> torch.Tensor:
    """The bucket rule as it was written before 2026-12-02: three ``where`` in priority order."""
    tolerance = 1.0 + 1e-4
    off = torch.zeros_like(fresh)
    verify = (
        ~fresh & (span <= (c.verify_samples - 1) * c.max_step_px * tolerance) if c.verify_samples else off
    )
    short = ~fresh & (span <= c.short_samples * c.max_step_px)
    medium = span <= (c.medium_samples - 1) * c.max_step_px * tolerance if c.medium_samples else off
    bucket = torch.full_like(span, 3, dtype=torch.long)
    bucket = torch.where(medium, 2, bucket)
    bucket = torch.where(short, 1, bucket)
    return torch.where(verify, 0, bucket)


@pytest.mark.parametrize(
    'config',
    [
        FilterConfig(),
        FilterConfig(verify_samples=0),
        FilterConfig(medium_samples=0),
        FilterConfig(verify_samples=0, medium_samples=0),
        FilterConfig(short_samples=12, long_samples=40, medium_samples=13),
    ],
)
def test_bucket_members_follow_the_where_chain(config):
    gen = torch.Generator().manual_seed(3)
    span = torch.rand(5000, generator=gen) * 40.0
    # exactly on every threshold too
    c = config
    edges = [
        c.short_samples * c.max_step_px,
        (c.verify_samples - 1) * c.max_step_px,
        (c.medium_samples - 1) * c.max_step_px,
    ]
    span[: len(edges)] = torch.tensor(edges)
    fresh = torch.rand(5000, generator=gen) > 0.7
    expected = _where_chain(span, fresh, config)
    members = bucket_members(span, fresh, config)
    for k, rows in enumerate(members):
        assert torch.equal(rows, _nonzero(expected == k)), k
    assert torch.equal(plan_buckets(span, fresh, config), expected)


def _keyframe(m: int, gen: torch.Generator) -> SimpleNamespace:
    prior = torch.rand(m, generator=gen) > 0.3
    # Beta counts near the reset line, so some rows fall below the inlier ratio
    a = torch.rand(m, generator=gen) * 12 + 1
    b = torch.rand(m, generator=gen) * 12 + 1
    state = BetaGaussian(torch.rand(m, generator=gen) + 0.2, torch.rand(m, generator=gen) * 1e-2 + 1e-5, a, b)
    updates = torch.where(prior, torch.randint(1, 9, (m,), generator=gen), 0)
    cost = torch.where(prior, torch.rand(m, generator=gen), math.nan)
    return SimpleNamespace(state=state, updates=updates, prior=prior, cost=cost)


def _copy(key: SimpleNamespace) -> SimpleNamespace:
    s = key.state
    return SimpleNamespace(
        state=BetaGaussian(s.mu.clone(), s.var.clone(), s.a.clone(), s.b.clone()),
        updates=key.updates.clone(),
        prior=key.prior.clone(),
        cost=key.cost.clone(),
    )


@pytest.mark.parametrize('seed', [0, 1, 2])
@pytest.mark.parametrize('pose_sigma', [0.0, 0.01])
def test_matches_update_only_the_rows_they_change(seed, pose_sigma):
    """The CPU's update of only the rows that change against the dense form (every row's
    posterior kept with ``where``), which the GPU runs and the CPU ran until 2026-12-02."""
    gen = torch.Generator().manual_seed(seed)
    m = 4000
    filt = SimpleNamespace(config=FilterConfig(pose_sigma=pose_sigma), rho_range=(0.1, 5.0))
    key = _keyframe(m, gen)
    rows = torch.randperm(m, generator=gen)[:2500]
    fresh = ~key.prior.index_select(0, rows)
    valid = torch.rand(2500, generator=gen) > 0.45
    x = torch.rand(2500, generator=gen) * 2 + 0.1
    j_x = torch.rand(2500, generator=gen) * 300 + 1
    cost = torch.rand(2500, generator=gen)
    dense, sparse = _copy(key), _copy(key)
    _apply_dense(filt, dense, Matches(rows, x, j_x, cost, fresh), valid, 0.05)
    apply_matches(filt, sparse, Matches(rows, x, j_x, cost, fresh), valid, 0.05)
    changed = 0
    for name in ('mu', 'var', 'a', 'b'):
        got, want = getattr(sparse.state, name), getattr(dense.state, name)
        assert torch.equal(got, want), name
        changed += int((want != getattr(key.state, name)).sum())
    for name in ('updates', 'prior'):
        assert torch.equal(getattr(sparse, name), getattr(dense, name)), name
    assert torch.equal(sparse.cost.nan_to_num(-1.0), dense.cost.nan_to_num(-1.0))
    # every branch was taken: first measurements, updates, votes and resets
    assert int((fresh & valid).sum()) > 0 and int((~fresh & ~valid).sum()) > 0
    assert int((key.prior & ~dense.prior).sum()) > 0  # estimates reset below the inlier ratio
    assert changed > 0


@pytest.mark.parametrize('n', [1, 2, 7, 7500])
def test_the_scene_depths_median_is_torchs(n):
    values = torch.rand(n, generator=torch.Generator().manual_seed(n))
    assert _lower_median(values) == float(torch.median(values))
    assert _lower_median(values[::2]) == float(torch.median(values[::2]))
