"""The mount check's stacked pairs: every pair's cost under every turn in one pass, the same as
a pass per pair (``multiview/pair_stack.py``)."""

from __future__ import annotations

import numpy as np
import pytest
from test_mount_check import _exact_pairs

from depth_fusion_ros.multiview.epipolar_cost import pose_costs
from depth_fusion_ros.multiview.mount_check import _turns
from depth_fusion_ros.multiview.pair_stack import PairStack


def test_the_stacked_costs_are_each_pairs_own():
    """Pairs of different sizes under 7 turns: each pair's mean cost is what a pass over that pair
    alone gives (to 1e-12), a pose that does not move costs inf, as one pass says, and a pair
    without matches is refused."""
    camera, pairs = _exact_pairs([1.0, -0.5, 0.2], 'forward', n_pairs=5)
    pairs[1] = type(pairs[1])(pairs[1].a, pairs[1].b, pairs[1].p1[:40], pairs[1].p2[:40])
    still = type(pairs[2])(pairs[2].a, pairs[2].a, pairs[2].p1, pairs[2].p2)  # no motion at all
    pairs.append(still)
    M = _turns(np.radians(np.random.default_rng(5).normal(0.0, 2.0, (7, 3))))
    stacked = PairStack.of(pairs).turned_costs(camera.K, M)
    assert stacked.shape == (7, len(pairs))
    for j, pair in enumerate(pairs):
        own = pose_costs(camera.K, np.transpose(M, (0, 2, 1)) @ pair.T_ba @ M, pair.p1, pair.p2)
        assert np.allclose(stacked[:, j], own, rtol=1e-12, atol=0.0, equal_nan=False), j
    assert np.isinf(stacked[:, -1]).all() and np.isfinite(stacked[:, :-1]).all()
    assert PairStack.of([]).turned_costs(camera.K, M).shape == (7, 0)
    empty = type(pairs[0])(pairs[0].a, pairs[0].b, pairs[0].p1[:0], pairs[0].p2[:0])
    with pytest.raises(ValueError, match='pair 1 has no matches'):
        PairStack.of([pairs[0], empty])


def test_a_kept_part_of_a_stack_is_the_stack_of_those_matches():
    """Leaving out a block of pairs and a region's matches (as the jackknifes do) gives the very
    arrays a stack of the remaining pairs gives, and a pair left with too few matches goes."""
    _, pairs = _exact_pairs([1.0, -0.5, 0.2], 'forward', n_pairs=4)
    stack = PairStack.of(pairs)
    without = stack.keep(stack.pair != 1)
    expected = PairStack.of([pairs[0], pairs[2], pairs[3]])
    left = stack.keep(stack.p1[:, 0] < 100.0, min_matches=100)
    kept = [(p, p.p1[:, 0] < 100.0) for p in pairs]
    by_pair = PairStack.of([type(p)(p.a, p.b, p.p1[k], p.p2[k]) for p, k in kept if k.sum() >= 100])
    for got, want in ((without, expected), (left, by_pair)):
        for name in ('T_ba', 'p1', 'p2', 'pair', 'starts', 'counts'):
            assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert len(without) == len(left) == 3  # pair 0 keeps 94 matches left of x = 100
