"""A frame's chosen rows of the filter's keyframe and their search intervals.

What ``filter_frame_update`` hands from the choice of rows and their intervals to the searches
(``search_rows`` in torch, ``native_rows`` in one native pass): one value instead of the same
nine tensors in every signature.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .filter_geometry import FrameGeometry


class ChosenRows(NamedTuple):
    """The keyframe rows one frame searches, each with its interval.

    ``rows`` (R,) the keyframe rows; ``a`` (3, R) their projections at infinity in the frame
    (pixels, coordinate-first) and ``geo`` the frame's geometry (its ``b``); ``lo``, ``hi``
    (R,) the inverse-depth intervals; ``j`` (R,) the epipolar motion at the prior; ``fresh``
    (R,) bool: no prior (a whole-range or bracketed search), ``seeds`` its positions;
    ``bracketed`` (R,) bool or None: the first searches narrowed to their neighbours' range.
    """

    rows: torch.Tensor
    a: torch.Tensor
    geo: FrameGeometry
    lo: torch.Tensor
    hi: torch.Tensor
    j: torch.Tensor
    fresh: torch.Tensor
    seeds: torch.Tensor
    bracketed: torch.Tensor | None
