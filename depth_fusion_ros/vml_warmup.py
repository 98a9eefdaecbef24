"""Resolve MKL VML's kernel dispatch once, on one thread, before any parallel use (imported for it).

Why: on CPU, ATen computes contiguous float unary ops (``sqrt``, ``exp``, ``log``, ``sin``,
``tanh``, ...) with MKL VML, each intra-op thread calling e.g. ``vmsSqrt(n, in, out, VML_HA)``
on its chunk. The oneMKL in the torch wheels (2024.2) picks each VML function's kernel lazily
on that function's first call, and when that first call runs on two threads at once, one of
them can run the low-accuracy AVX2 ``EP`` kernel for its whole chunk despite ``VML_HA``
(pytorch/pytorch#188791, #188792; fixed in oneMKL >= 2025.0). Here it hit the first
``torch.sqrt`` of a process, the descriptor norm of the filter's first frame
(``descriptors.patch_descriptors``): half of that frame's norms ~1e-4 off (up to ~4000 ulp),
matching the EP kernel bit for bit, so the whole filter run, and the evaluate MAEs, came out
different in about 3 % of processes (more often with the allocator tuning of
:mod:`.malloc_tuning`, which changes the threads' timing; seen without it too). A
one-element call per function and dtype runs on the calling thread only (below ATen's grain
size), resolves the dispatch, and every later call, parallel or not, then runs the requested
high-accuracy kernel.
"""

from __future__ import annotations

import threading

import torch

#: ATen's MKL VML unary ops (``aten/src/ATen/cpu/vml.h``, ``IMPLEMENT_VML_MKL``).
VML_OPS = (
    'sqrt',
    'exp',
    'log',
    'log2',
    'log10',
    'sin',
    'cos',
    'tan',
    'tanh',
    'asin',
    'acos',
    'atan',
    'erf',
    'erfc',
    'erfinv',
    'trunc',
)

_lock = threading.Lock()
_done = False


def warm_up_vml() -> None:
    """Call every VML-backed unary op once on a one-element float32 and float64 CPU tensor."""
    global _done
    with _lock:
        if _done:
            return
        with torch.no_grad():
            for dtype in (torch.float32, torch.float64):
                x = torch.full((1,), 0.5, dtype=dtype)
                for name in VML_OPS:
                    getattr(torch, name)(x)
        _done = True


warm_up_vml()
