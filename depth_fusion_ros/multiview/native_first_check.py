"""A frame's first measurements checked once more, in one native pass (``matching_cost.c``'s
``first_check``).

:func:`.filter_first_check.check_first_matches` searches every first measurement of a frame
again over +- ``filter.first_check_px`` pixels at one sample a pixel. The search itself was
already native (``native_cost.native_frame_search``); around it the torch code gathers the
rows' keys and rays, normalises the rays, builds the windows and writes the window's best
back: some twenty small ops a frame, about as long as the search (0.5 ms a frame on the
synthetic room, one thread). The kernel does the whole check per row, the same numbers bit for
bit (``test/test_native_first_check.py``). On CUDA, with a search the tests substitute, or
where the kernels cannot be built, the torch code runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from . import native_cost
from .filter_geometry import FrameGeometry
from .filter_keyframe import FilterKeyframe
from .filter_search import search_interval

if TYPE_CHECKING:
    from .filter import DepthFilter


def native_first_check(
    filt: DepthFilter,
    key: FilterKeyframe,
    rows: torch.Tensor,
    desc: torch.Tensor,
    a_r: torch.Tensor,
    geo: FrameGeometry,
    x: torch.Tensor,
    j_x: torch.Tensor,
    cost: torch.Tensor,
    valid: torch.Tensor,
) -> bool:
    """:func:`.filter_first_check.check_first_matches` in the kernel (``x``, ``j_x``, ``cost``
    and ``valid`` changed in place as there); ``False``, nothing done, where it does not apply:
    another search than the filter's own (a test's), rows or matches not of the filter's
    types, or the kernels' own conditions (``native_cost._ready``: a CPU, float32, at most
    seven channels, built here)."""
    c = filt.config
    n = int(rows.numel())
    samples = 2 * round(c.first_check_px) + 1  # one sample a pixel
    keys = key.key_desc
    shapes = (
        filt.search is search_interval,
        rows.dtype == torch.long and rows.is_contiguous() and rows.shape == (n,),
        valid.dtype == torch.bool and valid.is_contiguous() and valid.shape == (n,),
        all(t.is_contiguous() and t.shape == (n,) for t in (x, j_x, cost)),
        a_r.shape == (3, n) and a_r.stride(-1) == 1,
        key.updates.dtype == torch.long and key.updates.is_contiguous(),
        keys.dim() == 2 and keys.stride(-1) == 1 and keys.shape[1] == key.updates.numel(),
        desc.dim() == 4 and desc.shape[0] == 1,
        samples <= native_cost.SEARCH_MAX_SAMPLES,
    )
    ready = native_cost._ready(keys, desc, shapes, a_r, x, j_x, cost)
    if ready is None:
        return False
    lib, table = ready
    cam = filt.camera
    height, width = desc.shape[2], desc.shape[3]
    scale = torch.tensor([2.0 / (cam.width - 1), 2.0 / (cam.height - 1)], dtype=torch.float32).tolist()
    rho_min, rho_max = (float(v) for v in torch.tensor(filt.rho_range, dtype=torch.float32))
    scratch = torch.empty(n, dtype=torch.long)  # held here: the kernel writes into it
    lib.first_check(
        table.data_ptr(), height, width, keys.shape[0], keys.data_ptr(), keys.stride(0),
        rows.data_ptr(), key.updates.data_ptr(), a_r.data_ptr(), a_r.stride(0), *geo.b, *scale,
        x.data_ptr(), j_x.data_ptr(), cost.data_ptr(), valid.data_ptr(), n,
        float(c.first_check_px), samples, float(c.first_check_distinctiveness), rho_min, rho_max,
        scratch.data_ptr(), native_cost._threads(n * samples),
    )  # fmt: skip
    return True
