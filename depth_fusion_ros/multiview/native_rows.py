"""A frame's searches of the filter's chosen rows, their tests and the first-measurement check,
in one native pass (``matching_cost.c``'s ``filter_rows``).

Between the choice of rows and the update, :func:`.filter_frame_update._update_rows` searches
every chosen row (``search_rows``: the interval's length in pixels, the buckets, one native
search per bucket), tests each match (the motion there, a bracket's edge, the range) and checks
every first measurement once more at one sample a pixel (``filter_first_check``). The searches
themselves were native already; around them some fifty small torch ops a frame (sorting the rows
into buckets, gathering their keys and rays, normalising the rays, scattering the matches back,
the tests, the check's windows) cost about a fifth of a filter frame on one thread. The kernel
does it all per row, the same numbers bit for bit (``test/test_native_rows.py``). On CUDA, with a
search the tests substitute, or where the kernels cannot be built, the torch code runs.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import torch

from . import native_cost
from .filter_buckets import bucket_limits, search_buckets
from .filter_config import FilterConfig
from .filter_keyframe import FilterKeyframe
from .filter_rows import ChosenRows
from .filter_search import search_interval

if TYPE_CHECKING:
    from .filter import DepthFilter


def native_search_rows(
    filt: DepthFilter, key: FilterKeyframe, desc: torch.Tensor, chosen: ChosenRows
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """``(x, j_x, cost, valid)`` per chosen row as ``_update_rows`` has them before the update
    (the searches, the tests and the first-measurement check done), or ``None``, nothing done,
    where the kernel does not apply: another search than the filter's own (a test's), rows or
    intervals not of the filter's types, a bucket beyond the kernel's sample counts, or the
    kernels' own conditions (``native_cost._ready``: a CPU, float32, at most seven channels)."""
    c = filt.config
    rows, a_r, geo, lo, hi, j_r, fresh, _, bracketed = chosen
    n = int(rows.numel())
    buckets = search_buckets(c)
    check = 2 * round(c.first_check_px) + 1 if c.first_check_px > 0 else 3
    keys = key.key_desc
    flags = (fresh, *(() if bracketed is None else (bracketed,)))
    shapes = (
        filt.search is search_interval,
        rows.dtype == torch.long and rows.is_contiguous() and rows.shape == (n,),
        all(t.dtype == torch.bool and t.is_contiguous() and t.shape == (n,) for t in flags),
        all(t.is_contiguous() and t.shape == (n,) for t in (j_r, lo, hi)),
        a_r.shape == (3, n) and a_r.stride(-1) == 1,
        key.updates.dtype == torch.long and key.updates.is_contiguous(),
        keys.dim() == 2 and keys.stride(-1) == 1 and keys.shape[1] == key.updates.numel(),
        desc.dim() == 4 and desc.shape[0] == 1,
        all(_fits(samples, refine) for samples, refine, _ in buckets if samples > 0),
        _fits(check, 0),
    )
    ready = native_cost._ready(keys, desc, shapes, a_r, j_r, lo, hi)
    if ready is None:
        return None
    lib, table = ready
    cam = filt.camera
    # grid_sample's scale (filter_geometry.grid_rows_in_place) and the range: ctypes rounds each
    # to float32 as torch does
    scale = (2.0 / (cam.width - 1), 2.0 / (cam.height - 1))
    bucket_table, limits = _bucket_arrays(c)
    x, j_x, cost = (torch.empty(n, dtype=torch.float32) for _ in range(3))
    valid = torch.empty(n, dtype=torch.bool)
    scratch = torch.empty(2 * n, dtype=torch.long)
    lib.filter_rows(
        table.data_ptr(), desc.shape[2], desc.shape[3], keys.shape[0], keys.data_ptr(), keys.stride(0),
        rows.data_ptr(), key.updates.data_ptr(), fresh.data_ptr(),
        None if bracketed is None else bracketed.data_ptr(),
        a_r.data_ptr(), a_r.stride(0), *geo.b, *scale, j_r.data_ptr(), lo.data_ptr(), hi.data_ptr(), n,
        bucket_table.data_ptr(), limits.data_ptr(), float(c.max_cost), float(c.min_distinctiveness),
        int(c.reject_edge_minima), *filt.rho_range,
        float(c.first_check_px), check, float(c.first_check_distinctiveness),
        x.data_ptr(), j_x.data_ptr(), cost.data_ptr(), valid.data_ptr(), scratch.data_ptr(),
        native_cost._threads(native_cost.THREAD_MIN_LOOKUPS), native_cost.THREAD_MIN_LOOKUPS,
    )  # fmt: skip
    return x, j_x, cost, valid


@functools.lru_cache(maxsize=8)
def _bucket_arrays(config: FilterConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The buckets' samples, refinement and ratio switch (int32, 4 x 3) and their length limits
    (float32: short, verify, medium) as the kernel reads them, made once per configuration."""
    table = torch.tensor([v for bucket in search_buckets(config) for v in bucket], dtype=torch.int32)
    return table, torch.tensor(bucket_limits(config), dtype=torch.float32)


def _fits(samples: int, refine: int) -> bool:
    """Whether one search of ``samples`` coarse and ``refine`` fine samples a side fits the
    kernel's stack arrays (``frame_search``'s limits)."""
    return 3 <= samples <= native_cost.SEARCH_MAX_SAMPLES and 0 <= refine <= native_cost.SEARCH_MAX_REFINE
