"""The adaptation guard's paired test (``adaptation/guard.py``): a worsening is rolled back only
when it exceeds the tolerance by more than ``z`` standard errors of the per-point changes."""

from __future__ import annotations

import math

import pytest
import torch

from depth_fusion_ros.adaptation.guard import judge, paired_change


def _errors(n: int, mean: float, spread: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (mean + spread * torch.randn(n, generator=g)).abs()


def _update(before: list[torch.Tensor], shift: float, noise: float, seed: int) -> list[torch.Tensor]:
    """The same points after an update: each error moved by ``shift`` plus per-point noise."""
    g = torch.Generator().manual_seed(seed)
    return [(b + shift + noise * torch.randn(b.shape, generator=g)).abs() for b in before]


def test_paired_change_matches_its_definition():
    before = [torch.tensor([0.1, 0.2, 0.3]), torch.tensor([0.05, 0.15])]
    after = [torch.tensor([0.1, 0.25, 0.3]), torch.tensor([0.05, 0.05])]
    b, a, change, se = paired_change(before, after)
    assert b == pytest.approx((0.2 + 0.1) / 2)
    assert a == pytest.approx((0.65 / 3 + 0.05) / 2)
    assert change == pytest.approx(a - b)
    d = [torch.tensor([0.0, 0.05, 0.0]), torch.tensor([0.0, -0.1])]
    assert se == pytest.approx(math.sqrt(sum(float(x.var()) / x.numel() for x in d)) / 2, rel=1e-5)
    with pytest.raises(ValueError, match='same points'):
        paired_change([torch.zeros(3)], [torch.zeros(4)])


def test_a_worsening_within_the_noise_of_the_points_is_kept():
    # Five keyframes of 60 held-out points: errors ~0.05 with a spread of 0.09 (as measured on a
    # real sequence), an update that moves each point by +-0.02 and the mean by +0.0015 (3 %).
    before = [_errors(60, 0.05, 0.09, k) for k in range(5)]
    after = _update(before, 0.0015, 0.02, 10)
    bare = judge(before, after, tolerance=0.02, z=0.0)
    tested = judge(before, after, tolerance=0.02, z=2.33)
    assert bare.rolled_back  # the plain 2 % threshold rejects it
    assert not tested.rolled_back  # 3 % on 300 points is within ~1 standard error
    assert tested.after > tested.before * 1.02 and tested.keyframes == 5


def test_a_significant_worsening_is_rolled_back():
    before = [_errors(500, 0.05, 0.09, k) for k in range(5)]
    # The same small update on many points: now the points do show it.
    assert judge(before, _update(before, 0.004, 0.002, 11), tolerance=0.02, z=2.33).rolled_back
    # A poisoned update moves every point a lot, on few points as well.
    few = [b[:20] for b in before]
    assert judge(few, _update(few, 0.3, 0.05, 12), tolerance=0.02, z=2.33).rolled_back


def test_an_improvement_is_kept_and_broken_errors_are_rolled_back():
    before = [_errors(100, 0.05, 0.09, k) for k in range(3)]
    assert not judge(before, _update(before, -0.01, 0.01, 13), 0.02, 2.33).rolled_back
    broken = [b.clone() for b in before]
    broken[1][4] = float('nan')
    assert judge(before, broken, 0.02, 2.33).rolled_back
    empty = judge([], [], 0.02, 2.33)
    assert not empty.rolled_back and empty.keyframes == 0 and math.isnan(empty.before)
