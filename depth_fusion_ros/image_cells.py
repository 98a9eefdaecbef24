"""Square cells over an image, and which cell each pixel position falls in.

Two tests ask how points spread over a view: the filter's minority test per region
(``multiview/filter.py``: a cell whose passing estimates are a sliver publishes none) and the
adaptation's coverage (``adaptation/sample.py``: the share of cells holding training points).
Both cut the image the same way, here: ``across`` square cells over the width, rows in
proportion (8 across is 8 x 6 at 4:3, 40 px at 320x240), the last row and column possibly
partial. Works on numpy arrays and torch tensors alike (the filter's are on its device).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch

Array = TypeVar('Array', np.ndarray, torch.Tensor)


@dataclass(frozen=True)
class ImageCells:
    """``columns`` x ``rows`` square cells of ``side`` pixels over a ``width`` x ``height`` image."""

    side: int
    columns: int
    rows: int

    @classmethod
    def across(cls, width: int, height: int, across: int) -> ImageCells:
        """``across`` cells over the width (at least 1 px each), as many rows as the height needs."""
        if across < 1:
            raise ValueError(f'cells across must be >= 1, got {across}')
        side = max(1, math.ceil(width / across))
        return cls(side, math.ceil(width / side), math.ceil(height / side))

    @property
    def count(self) -> int:
        return self.columns * self.rows

    def index(self, u: Array, v: Array) -> Array:
        """Flat cell index (row-major, int64) of pixel positions ``u`` (column), ``v`` (row);
        positions outside the image are clamped to its border cells."""
        if isinstance(u, torch.Tensor):
            col = torch.clamp(torch.div(u, self.side, rounding_mode='floor').long(), 0, self.columns - 1)
            row = torch.clamp(torch.div(v, self.side, rounding_mode='floor').long(), 0, self.rows - 1)
        else:
            col = np.clip(np.floor_divide(np.asarray(u), self.side).astype(np.int64), 0, self.columns - 1)
            row = np.clip(np.floor_divide(np.asarray(v), self.side).astype(np.int64), 0, self.rows - 1)
        return row * self.columns + col
