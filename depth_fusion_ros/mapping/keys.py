"""Integer 3-D coordinates as sortable int64 keys, and lookups in a sorted key table.

torch has no hash map, so the sparse voxel map looks coordinates up by binary search in a
sorted key table (``searchsorted``): vectorised, identical on CPU and CUDA, and O(log n) per
query. 21 bits per axis hold ±1 M cells (±42 km at 4 cm voxels).
"""

from __future__ import annotations

import torch

BITS = 21
OFFSET = 1 << (BITS - 1)
MASK = (1 << BITS) - 1


def pack(coords: torch.Tensor) -> torch.Tensor:
    """(..., 3) int64 cell coordinates -> (...) int64 keys (order: x, then y, then z)."""
    c = coords.to(torch.int64) + OFFSET
    return (c[..., 0] << (2 * BITS)) | (c[..., 1] << BITS) | c[..., 2]


def unpack(keys: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`pack`: (...) keys -> (..., 3) int64 coordinates."""
    x = (keys >> (2 * BITS)) & MASK
    y = (keys >> BITS) & MASK
    z = keys & MASK
    return torch.stack((x, y, z), dim=-1) - OFFSET


class SortedKeys:
    """A read-only index ``key -> row``: the keys sorted once, then binary-searched."""

    def __init__(self, keys: torch.Tensor) -> None:
        self.sorted, self.order = torch.sort(keys)

    def lookup(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows, found): the row of each query key in the original table, and whether it exists."""
        if self.sorted.numel() == 0:
            empty = torch.zeros_like(queries)
            return empty, torch.zeros(queries.shape, dtype=torch.bool, device=queries.device)
        pos = torch.searchsorted(self.sorted, queries).clamp_(max=self.sorted.numel() - 1)
        found = self.sorted[pos] == queries
        return self.order[pos], found
