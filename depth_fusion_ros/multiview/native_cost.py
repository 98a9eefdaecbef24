"""The epipolar matching cost on a CPU in one native pass per lookup (``matching_cost.c``).

The filter's per-frame search (``filter_search._frame_cost``) and the sweep's cost volume
(``cost_volume.sample_cost``) are most of the multi-view time on a CPU: a bilinear lookup of
the descriptors (ATen's ``grid_sample``) at every sample, then the ZNCC with the row's key
descriptor and the normalisation, each a pass over memory. The C kernels do all of it per
sample, from a channels-last copy of the descriptors made once per frame, and write only the
cost (for the filter, only each row's match: ``native_frame_search``): the same numbers (bit
for bit where checked, ``test_native_matching_cost.py``) in about a third of the time on one
core. They serve the CPU only: on CUDA, or where the kernels cannot
be built (``native_build.load_native``), or for a descriptor of more than seven channels, the
functions here return ``None`` and the torch code runs.
"""

from __future__ import annotations

import ctypes
import sys
import threading
from collections import OrderedDict
from pathlib import Path

import torch

from ..native_build import kernel_threads, load_native

#: The kernels' channels-last block: the descriptor channels and the visibility, padded.
LANES = 8
#: Lookups below which one call does not go to the threads (the hand-over costs more).
THREAD_MIN_LOOKUPS = 1 << 16
#: Descriptor tables kept (a frame's, a keyframe's neighbours'): the searches of one frame and
#: the chunks of one sweep share theirs.
TABLES_KEPT = 4

_SOURCE = Path(__file__).with_name('matching_cost.c')
_P, _I, _I64, _F = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64, ctypes.c_float
#: A frame's arguments (table, H, W, C, key, key stride, a, a stride, b0, b1, b2).
_FRAME = (_P, _I, _I, _I, _P, _I64, _P, _I64, _F, _F, _F)
#: filter_rows' arguments after the frame's first six: rows, updates, fresh, bracketed, a, its
#: stride, b, the scale, j, lo, hi, R, the buckets and limits, the tests, the range, the check
#: (px, samples, ratio), the outputs, the scratch, the threads and the lookups below which a
#: search stays on one thread.
_ROWS = (_P, _P, _P, _P, _P, _I64, _F, _F, _F, _F, _F, _P, _P, _P, _I64,
         _P, _P, _F, _F, _I, _F, _F, _F, _I, _F, _P, _P, _P, _P, _P, _I, _I64)  # fmt: skip
_SIGNATURES = {
    'frame_cost': [*_FRAME, _P, _I64, _I, _I64, _P, _I],
    'sweep_cost': [_P, _I, _I, _I, _I, _P, _I64, _P, _I64, _P, _P, _I64, _I, _P, _P, _I],
    # then lo, hi, R, S, refine, the two switches, the four outputs, the threads
    'frame_search': [*_FRAME, _P, _P, _I64, _I, _I, _I, _I, _P, _P, _P, _P, _I],
    'channels_last': [_P, _I, _I, _I64, _I64, _I64, _I64, _P, _I],
    'filter_rows': [*_FRAME[:6], *_ROWS],
}
#: The most coarse samples and fine samples a side of one native search (its stack arrays).
SEARCH_MAX_SAMPLES, SEARCH_MAX_REFINE = 512, 64
_lock = threading.Lock()
_tables: OrderedDict[int, tuple[torch.Tensor, int, torch.Tensor]] = OrderedDict()
#: Tables dropped from ``_tables`` that nothing holds, by shape, for reuse (:func:`_keep_spare`).
_spares: dict[tuple[int, ...], torch.Tensor] = {}


def native_frame_cost(
    key_desc: torch.Tensor, frame_desc: torch.Tensor, a: torch.Tensor, b: torch.Tensor, rho: torch.Tensor
) -> torch.Tensor | None:
    """``filter_search._frame_cost`` (S, R) by the native kernel, or ``None`` where it does not
    apply (then the caller's torch code runs): ``key_desc`` (C, R), ``frame_desc`` (1, C + 1, H,
    W), ``a`` (3, R) and ``b`` (3,) the rows' normalised rays, ``rho`` (S, R)."""
    rows = key_desc.shape[1]
    shapes = (frame_desc.dim() == 4 and frame_desc.shape[0] == 1, a.shape == (3, rows), b.shape == (3,))
    ready = _ready(key_desc, frame_desc, (*shapes, rho.dim() == 2 and rho.shape[1] == rows), a, b, rho)
    if ready is None:
        return None
    lib, table = ready
    channels, height, width = key_desc.shape[0], frame_desc.shape[2], frame_desc.shape[3]
    key_desc, a = (t if t.stride(-1) == 1 else t.contiguous() for t in (key_desc, a))
    rho = rho.contiguous()
    samples = rho.shape[0]
    out = torch.empty((samples, rows), dtype=torch.float32)
    b0, b1, b2 = (float(v) for v in b.tolist())

    lib.frame_cost(
        table.data_ptr(), height, width, channels,
        key_desc.data_ptr(), key_desc.stride(0), a.data_ptr(), a.stride(0), b0, b1, b2,
        rho.data_ptr(), rows, samples, rows, out.data_ptr(), _threads(samples * rows),
    )  # fmt: skip
    return out


def native_frame_search(
    key_desc: torch.Tensor,
    frame_desc: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    samples: int,
    refine: int,
    with_distinctiveness: bool,
    reject_edges: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """``filter_search._search_rows`` whole (rho, cost, distinct, ok per row) by the native
    kernel, or ``None`` where it does not apply: the coarse samples, the best and its
    distinctiveness, the fine samples and the parabola of each row in one pass, instead of some
    forty torch ops over the bucket. ``key_desc`` (C, R), ``frame_desc`` (1, C + 1, H, W),
    ``a`` (3, R) and ``b`` (3,) the rows' normalised rays, ``lo`` and ``hi`` (R,)."""
    rows = key_desc.shape[1]
    shapes = (
        frame_desc.dim() == 4 and frame_desc.shape[0] == 1,
        a.shape == (3, rows),
        b.shape == (3,),
        lo.shape == (rows,) and hi.shape == (rows,),
        3 <= samples <= SEARCH_MAX_SAMPLES and 0 <= refine <= SEARCH_MAX_REFINE,
    )
    ready = _ready(key_desc, frame_desc, shapes, a, b, lo, hi)
    if ready is None:
        return None
    lib, table = ready
    channels, height, width = key_desc.shape[0], frame_desc.shape[2], frame_desc.shape[3]
    key_desc, a = (t if t.stride(-1) == 1 else t.contiguous() for t in (key_desc, a))
    lo, hi = lo.contiguous(), hi.contiguous()
    rho, cost, distinct = (torch.empty(rows, dtype=torch.float32) for _ in range(3))
    ok = torch.empty(rows, dtype=torch.bool)
    b0, b1, b2 = (float(v) for v in b.tolist())

    lib.frame_search(
        table.data_ptr(), height, width, channels,
        key_desc.data_ptr(), key_desc.stride(0), a.data_ptr(), a.stride(0), b0, b1, b2,
        lo.data_ptr(), hi.data_ptr(), rows, samples, refine, int(with_distinctiveness), int(reject_edges),
        rho.data_ptr(), cost.data_ptr(), distinct.data_ptr(), ok.data_ptr(),
        _threads(rows * (samples + 2 * refine)),
    )  # fmt: skip
    return rho, cost, distinct, ok


def native_sweep_cost(
    key_desc: torch.Tensor, neighbour_desc: torch.Tensor, a: torch.Tensor, b: torch.Tensor, rho: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``cost_volume.sample_cost``'s cost and count (M, S) by the native kernel, or ``None``:
    ``key_desc`` (C, M), ``neighbour_desc`` (n, C + 1, H, W), ``a`` (n, M, 3) and ``b`` (n, 3)
    the rays normalised (``EpipolarRays._normalised``), ``rho`` (S,) or (M, S)."""
    n, rows = neighbour_desc.shape[0], key_desc.shape[1]
    shapes = (neighbour_desc.dim() == 4, a.shape == (n, rows, 3), b.shape == (n, 3))
    per_sample = rho.dim() == 1 or (rho.dim() == 2 and rho.shape[0] == rows)
    ready = _ready(key_desc, neighbour_desc, (*shapes, per_sample), a, b, rho)
    if ready is None:
        return None
    lib, table = ready
    height, width = neighbour_desc.shape[2], neighbour_desc.shape[3]
    channels = key_desc.shape[0]
    key_desc = key_desc if key_desc.stride(-1) == 1 else key_desc.contiguous()
    a, b, rho = a.contiguous(), b.contiguous(), rho.contiguous()
    samples = rho.shape[-1]
    row_stride = samples if rho.dim() == 2 else 0
    cost = torch.empty((rows, samples), dtype=torch.float32)
    count = torch.empty((rows, samples), dtype=torch.float32)

    lib.sweep_cost(
        table.data_ptr(), n, height, width, channels, key_desc.data_ptr(), key_desc.stride(0),
        a.data_ptr(), rows, b.data_ptr(), rho.data_ptr(), row_stride, samples,
        cost.data_ptr(), count.data_ptr(), _threads(n * samples * rows),
    )  # fmt: skip
    return cost, count


def prepare() -> bool:
    """Build (first run on this machine, well under a second) or load the kernels now, so that
    a node's first frame does not wait for the compiler; whether they will be used."""
    return _library() is not None


def _ready(
    key_desc: torch.Tensor, desc: torch.Tensor, shapes: tuple[bool, ...], *rest: torch.Tensor
) -> tuple[ctypes.CDLL, torch.Tensor] | None:
    """The library and the descriptors' table for a kernel call, or None where the call does
    not apply: a shape the caller's checks refused (``shapes``: never a read out of bounds), not
    CPU float32, descriptors and visibility beyond one 8-float block, or no kernels here."""
    applies = (
        all(shapes)
        and desc.device.type == 'cpu'
        and key_desc.shape[0] + 1 <= LANES
        and desc.shape[1] == key_desc.shape[0] + 1
        and all(t.dtype == torch.float32 for t in (key_desc, desc, *rest))
    )
    lib = _library() if applies else None
    return None if lib is None else (lib, _channels_last(lib, desc))


def _threads(lookups: int) -> int:
    """The call's threads (``native_build.kernel_threads``), read at the call: the tests lower
    :data:`THREAD_MIN_LOOKUPS`."""
    return kernel_threads(lookups, THREAD_MIN_LOOKUPS)


def _library() -> ctypes.CDLL | None:
    """The kernels' library (built on first use), or None."""
    return load_native(_SOURCE, _SIGNATURES)


def _channels_last(lib: ctypes.CDLL, desc: torch.Tensor) -> torch.Tensor:
    """Descriptors (n, C + 1, H, W) as n tables of (H * W + 1, 8) one after the other: a pixel's
    channels in one block, then a zero block (what a kernel reads for a corner outside the
    image). Made once per descriptor tensor (kept by identity and version: a frame's searches
    and a sweep's chunks share theirs), by the kernels' own copy (planar descriptors
    transposed eight pixels at a time, interleaved ones read in place: a third of the time of
    torch's permuted copy or less), into a dropped table's memory where one is free. Descriptors
    written as a table in the first place (the CPU's, ``descriptors._interleave``) are read in
    place (:func:`_table_in_place`)."""
    in_place = _table_in_place(desc)
    if in_place is not None:
        return in_place
    key = id(desc)
    # An inference tensor (made under torch.inference_mode) has no version counter and may
    # change in place unseen: its table is made for each call and not kept.
    version = None if desc.is_inference() else desc._version
    with _lock:
        kept = _tables.get(key)
        if kept is not None and kept[0] is desc and version is not None and kept[1] == version:
            _tables.move_to_end(key)
            return kept[2]
    n, ch, height, width = desc.shape
    shape = (n, height * width + 1, LANES)
    with _lock:
        table = _spares.pop(shape, None)
    if table is None:
        table = torch.empty(shape, dtype=torch.float32)
    # Pixels one stride apart in raster order (planar, or interleaved as the filter's frame
    # descriptors are): read in place; anything else is made contiguous first.
    flat, step = desc, _pixel_stride(desc)
    if step is None:
        flat = desc.contiguous()
        step = _pixel_stride(flat)
    pixels = height * width
    strides = (flat.stride(0), flat.stride(1), step)
    lib.channels_last(flat.data_ptr(), n, ch, pixels, *strides, table.data_ptr(), _threads(n * pixels))
    if version is None:
        return table
    with _lock:
        _tables[key] = (desc, version, table)
        _tables.move_to_end(key)
        while len(_tables) > TABLES_KEPT:
            _keep_spare(_tables.popitem(last=False)[1][2])
    return table


def _table_in_place(desc: torch.Tensor) -> torch.Tensor | None:
    """The table ``desc`` already is, or None: one image's descriptors (1, C + 1, H, W) whose
    pixels are blocks of :data:`LANES` floats from the start of their memory, followed in it by
    one zero block (what a corner outside the image reads). The spare lanes of a block are
    never read as channels, so only the zero block is checked."""
    n, _, height, width = desc.shape
    pixels = height * width
    if n != 1 or desc.storage_offset() != 0 or tuple(desc.stride()[1:]) != (1, width * LANES, LANES):
        return None
    if desc.untyped_storage().nbytes() != (pixels + 1) * LANES * desc.element_size():
        return None
    table = desc.as_strided((1, pixels + 1, LANES), ((pixels + 1) * LANES, LANES, 1), 0)
    return None if bool(table[0, pixels].any()) else table


def _pixel_stride(desc: torch.Tensor) -> int | None:
    """The stride between a (n, C, H, W) tensor's pixels in raster order, or None where they are
    not evenly spaced. A dimension of size 1 may carry any stride (torch ignores it), so only
    the strides that are ever stepped are read."""
    height, width = desc.shape[2], desc.shape[3]
    if width == 1:
        return desc.stride(2)
    if height == 1 or desc.stride(2) == width * desc.stride(3):
        return desc.stride(3)
    return None


def _keep_spare(table: torch.Tensor) -> None:
    """Keep a table dropped from the cache for the next one of its shape, unless a kernel call
    still holds it. Why: a new table each frame (2.4 MB at 320x240) is fresh memory from the
    system, and its page faults cost more than copying the descriptors into it (0.8 against
    0.4 ms a frame here). A table is only referenced from the cache and, during a call, from
    that call's frame: a count beyond the two of this call (its argument and getrefcount's)
    means in use (test_native_matching_cost.py checks the count)."""
    if sys.getrefcount(table) <= 2 and len(_spares) < TABLES_KEPT:
        _spares[tuple(table.shape)] = table
