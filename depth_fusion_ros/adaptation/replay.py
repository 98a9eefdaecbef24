"""A bounded buffer of past keyframes, replayed next to each new one (against forgetting).

Training only on the newest keyframe pulls the network towards the current view and away
from the rest of the scene (catastrophic forgetting; CoMoDA, Zhang et al. CVPR 2020). Each
step therefore also trains on a few keyframes drawn from this buffer. It holds the most
recent ``capacity`` keyframes; draws are seeded so an offline run is reproducible.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from typing import Generic, TypeVar

import numpy as np

T = TypeVar('T')


class ReplayBuffer(Generic[T]):
    """The last ``capacity`` items; ``draw`` picks distinct ones uniformly at random."""

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f'replay buffer capacity must be >= 1, got {capacity}')
        self.capacity = int(capacity)
        self._items: deque[T] = deque(maxlen=self.capacity)

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self) -> Iterator[T]:
        return iter(self._items)

    def add(self, item: T) -> None:
        self._items.append(item)

    def clear(self) -> None:
        self._items.clear()

    def recent(self, count: int) -> list[T]:
        """The ``count`` most recent items, newest first."""
        if count <= 0:
            return []
        return list(self._items)[-count:][::-1]

    def draw(self, count: int, rng: np.random.Generator) -> list[T]:
        """Up to ``count`` distinct items chosen uniformly (fewer when the buffer is smaller)."""
        n = min(int(count), len(self._items))
        if n <= 0:
            return []
        picks = rng.choice(len(self._items), size=n, replace=False)
        return [self._items[int(i)] for i in picks]
