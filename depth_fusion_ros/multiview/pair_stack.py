"""A check's image pairs stacked into one set of arrays, so that the epipolar costs of every pair
under S candidate turns are one numpy pass instead of one per pair.

Why: the mount check fits its rotation by Levenberg-Marquardt over all its pairs, at each new
pair from ``early_pairs`` on, again without each block of pairs (the jackknife) and without
each image region. Each evaluation is 19 candidate turns of 20 pairs of ~250 matches: small
arrays, so a pass per pair cost its numpy call overhead many times over, not its arithmetic.
Stacked, the matches of all pairs meet their own pair's fundamental matrix in one gather.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..geometry import skews
from .epipolar_cost import soft_l1_sampson_entries
from .image_pairs import MatchedPair

#: A relative pose that moves less than this (m) has no epipolar geometry: its cost is ``inf``.
_MIN_MOTION = 1e-5


@dataclass(frozen=True)
class PairStack:
    """The pairs' told relative poses (P, 4, 4) and their matches end to end: ``p1``, ``p2``
    (N, 2), ``pair`` (N,) the pair each match belongs to, ``starts`` (P,) where each pair's
    matches begin and ``counts`` (P,) how many there are. Made once per set of pairs a fit
    minimises over (:meth:`of`), read by each of its evaluations."""

    T_ba: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    pair: np.ndarray
    starts: np.ndarray
    counts: np.ndarray

    @classmethod
    def of(cls, pairs: list[MatchedPair]) -> PairStack:
        """The stack of ``pairs``, in their order; a pair without matches is an error (the checks'
        pairs keep at least ``min_matches``; a pair's mean cost needs one)."""
        counts = np.array([len(p.p1) for p in pairs], dtype=np.int64)
        if (counts == 0).any():
            raise ValueError(f'PairStack: pair {int(np.argmin(counts))} has no matches')
        if not pairs:
            return cls._made(np.zeros((0, 4, 4)), np.zeros((0, 2)), np.zeros((0, 2)), counts)
        return cls._made(
            np.array([p.T_ba for p in pairs], dtype=np.float64),
            np.concatenate([p.p1 for p in pairs]).astype(np.float64),
            np.concatenate([p.p2 for p in pairs]).astype(np.float64),
            counts,
        )

    @classmethod
    def _made(cls, T_ba: np.ndarray, p1: np.ndarray, p2: np.ndarray, counts: np.ndarray) -> PairStack:
        """A stack of its poses, matches and each pair's match count (the rest follows from them)."""
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        return cls(T_ba, p1, p2, np.repeat(np.arange(len(counts)), counts), starts[: len(counts)], counts)

    def with_poses(self, T_ba: np.ndarray) -> PairStack:
        """The same matches under other relative poses (P, 4, 4), one per pair: the pairs as
        another reading of the told poses would pose them (``pose_inversion.py``)."""
        return dataclasses.replace(self, T_ba=np.asarray(T_ba, dtype=np.float64))

    def keep(self, matches: np.ndarray, min_matches: int = 1) -> PairStack:
        """The stack with only the ``matches`` (a mask (N,)) kept, and only the pairs left with at
        least ``min_matches`` of them: the mount check's jackknifes leave out a block of pairs or
        a region of the image this way, without making pairs anew."""
        left = np.bincount(self.pair[matches], minlength=len(self))
        pairs = left >= max(int(min_matches), 1)
        matches = matches & pairs[self.pair]
        return self._made(self.T_ba[pairs], self.p1[matches], self.p2[matches], left[pairs])

    def __len__(self) -> int:
        return len(self.counts)

    def turned_costs(self, K: np.ndarray, M: np.ndarray) -> np.ndarray:
        """Mean soft-L1 Sampson cost (S, P) of each pair's matches when its told relative pose is
        read in a camera turned by each of S turns ``M`` (S, 4, 4): ``M^T T_ba M``, i.e. its
        rotation conjugated and its translation turned; ``inf`` where a turned pose does not move."""
        if not len(self):  # no pairs (a jackknife left out the only ones): nothing to cost
            return np.zeros((len(M), 0))
        T = np.transpose(M, (0, 2, 1))[:, None] @ self.T_ba[None] @ M[:, None]  # (S, P, 4, 4)
        S, P = T.shape[:2]
        t = T[..., :3, 3]
        Ki = np.linalg.inv(K)
        F = Ki.T @ skews(t.reshape(-1, 3)).reshape(S, P, 3, 3) @ T[..., :3, :3] @ Ki
        entries = np.transpose(F, (2, 3, 0, 1))[..., self.pair]  # (3, 3, S, N): each match its pair's F
        costs = soft_l1_sampson_entries(entries, self.p1, self.p2)
        means = np.add.reduceat(costs, self.starts, axis=1) / self.counts
        return np.where(np.linalg.norm(t, axis=-1) >= _MIN_MOTION, means, np.inf)
