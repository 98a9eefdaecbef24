"""The filter's per-frame matching cost on a CPU in one native pass (``frame_cost.c``).

``filter_search._frame_cost`` is most of the depth filter's search: a bilinear lookup of the
frame's descriptors (ATen's ``grid_sample``) at every sample of every searched row, then the
ZNCC with the row's key descriptor and the normalisation, each a pass over memory. The C
kernel does all of it per sample, from a channels-last copy of the frame's descriptors made
once per frame, and writes only the cost: the same numbers (bit for bit where checked,
``test_native_frame_cost.py``) in about a third of the time on one core. It serves the CPU
only: on CUDA, or where the kernel cannot be built (``native_build.load_native``), or for a
descriptor of more than seven channels, :func:`native_frame_cost` returns ``None`` and the
torch code runs.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from ..native_build import load_native

#: The kernel's channels-last block: the descriptor channels and the visibility, padded.
LANES = 8
#: Lookups below which one call does not go to the threads (the hand-over costs more).
THREAD_MIN_LOOKUPS = 1 << 16

_SOURCE = Path(__file__).with_name('frame_cost.c')
_lock = threading.Lock()
_kernel: ctypes._CFuncPtr | None = None  # type: ignore[name-defined]
_kernel_loaded = False
_last: tuple[torch.Tensor, int, torch.Tensor] | None = None  # (descriptors, their version, channels-last)
_pool: ThreadPoolExecutor | None = None
_pool_key = (0, 0)  # (threads, pid) it was made for


def native_frame_cost(
    key_desc: torch.Tensor, frame_desc: torch.Tensor, a: torch.Tensor, b: torch.Tensor, rho: torch.Tensor
) -> torch.Tensor | None:
    """``filter_search._frame_cost`` (S, R) by the native kernel, or ``None`` where it does not
    apply (then the caller's torch code runs): ``key_desc`` (C, R), ``frame_desc`` (1, C + 1, H,
    W), ``a`` (3, R) and ``b`` (3,) the rows' normalised rays, ``rho`` (S, R)."""
    channels = key_desc.shape[0]
    if (
        frame_desc.device.type != 'cpu'
        or frame_desc.dim() != 4
        or frame_desc.shape[0] != 1
        or channels + 1 > LANES
        or frame_desc.shape[1] != channels + 1
        or any(t.dtype != torch.float32 for t in (key_desc, frame_desc, a, b, rho))
    ):
        return None
    kernel = _load()
    if kernel is None:
        return None
    table = _channels_last(frame_desc)
    key_desc, a, rho = (t if t.stride(-1) == 1 else t.contiguous() for t in (key_desc, a, rho))
    rho = rho if rho.stride(0) == rho.shape[1] else rho.contiguous()
    samples, rows = rho.shape
    out = torch.empty((samples, rows), dtype=torch.float32)
    height, width = frame_desc.shape[2], frame_desc.shape[3]
    b0, b1, b2 = (float(v) for v in b.tolist())

    def run(start: int, stop: int) -> None:
        kernel(
            table.data_ptr(), height, width, channels,
            key_desc.data_ptr() + 4 * start, key_desc.stride(0),
            a.data_ptr() + 4 * start, a.stride(0),
            b0, b1, b2,
            rho.data_ptr() + 4 * start, rows, samples, stop - start,
            out.data_ptr() + 4 * start,
        )  # fmt: skip

    _split(run, rows, samples * rows)
    return out


def prepare() -> bool:
    """Build (first run on this machine, well under a second) or load the kernel now, so that
    a node's first frame does not wait for the compiler; whether it will be used."""
    return _load() is not None


def _split(run, rows: int, lookups: int) -> None:
    """``run`` over the rows, in one call or one slice per torch thread (the kernel lets go of
    the GIL): each slice is computed alone, so the numbers do not depend on the split."""
    threads = torch.get_num_threads()
    if threads <= 1 or lookups < THREAD_MIN_LOOKUPS or rows < 16 * threads:
        run(0, rows)
        return
    step = -(-rows // threads)
    step += -step % 8  # whole blocks of eight rows for the vector code
    bounds = [(s, min(s + step, rows)) for s in range(0, rows, step)]
    pool = _threads(threads)
    others = [pool.submit(run, s, e) for s, e in bounds[1:]]
    run(*bounds[0])
    for done in others:
        done.result()


def _threads(n: int) -> ThreadPoolExecutor:
    """``n - 1`` worker threads (the caller is the n-th), made anew for another count or in a
    forked child (a node started by the fork server: the parent's threads are not there)."""
    global _pool, _pool_key
    with _lock:
        if _pool is None or _pool_key != (n, os.getpid()):
            if _pool is not None and _pool_key[1] == os.getpid():
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(max_workers=n - 1, thread_name_prefix='frame_cost')
            _pool_key = (n, os.getpid())
        return _pool


def _load():
    """The kernel's ctypes function (built on first use), or None."""
    global _kernel, _kernel_loaded
    with _lock:
        if not _kernel_loaded:
            lib = load_native(_SOURCE)
            if lib is not None:
                p, i, i64, f = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64, ctypes.c_float
                fn = lib.frame_cost
                fn.argtypes = [p, i, i, i, p, i64, p, i64, f, f, f, p, i64, i, i64, p]
                fn.restype = None
                _kernel = fn
            _kernel_loaded = True
        return _kernel


def _channels_last(frame_desc: torch.Tensor) -> torch.Tensor:
    """The frame's descriptors as (H * W + 1, 8): a pixel's channels in one block, then a zero
    block (what the kernel reads for a corner outside the image). Made once per frame: the
    searches of a frame (its buckets, the first-measurement check) share it."""
    global _last
    with _lock:
        if _last is not None and _last[0] is frame_desc and _last[1] == frame_desc._version:
            return _last[2]
    _, ch, height, width = frame_desc.shape
    table = torch.zeros((height * width + 1, LANES), dtype=torch.float32)
    table[:-1, :ch] = frame_desc[0].permute(1, 2, 0).reshape(height * width, ch)
    with _lock:
        _last = (frame_desc, frame_desc._version, table)
    return table
