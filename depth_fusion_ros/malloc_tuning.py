"""Keep freed heap memory in the process instead of handing it back to the OS (glibc only).

Why: every keyframe the hot loops allocate and free tensors of 1-16 MB (the sweep's
descriptor stacks and cost chunks, the filter's per-frame buffers, the fusion's chunks).
glibc serves an allocation above its mmap threshold (128 KB, raised dynamically) with fresh
``mmap`` pages that ``free`` unmaps again, and it trims the heap top above 128 KB, so the next
tensor faults its memory in again, 4 KB at a time: 2,000-6,000 page faults per sweep
keyframe here, and with two torch threads they also contend for the process's memory map.
Raising both thresholds (what the ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``
variables do, and the reason PyTorch's CPU tuning guides suggest jemalloc or tcmalloc)
keeps the pages: measured on 2 cores, the sweep went from 41.7 to 34.8 ms a keyframe
(docs/performance.md, "Allocator"). The cost is that a process keeps the memory it once
used (its peak) instead of shrinking after it; every buffer here is bounded, so that peak
is too, **per malloc arena**. glibc gives threads arenas of their own (up to 8 per core), and
each keeps its own peak: the map node, whose integration, surface extraction and rebuild run
on threads of their own, grew from ~400 MB to 0.9-1.1 GB within 90 s of a looped replay
(`DEPTH_FUSION_SOAK_MAP_BLOCKS=300 scripts/soak.sh`, 2026-11-29). So the arenas are capped at
``ARENA_MAX`` (2, what ``MALLOC_ARENA_MAX=2`` does): the same run then held it at 400-500 MB.

**On by default; ``DEPTH_FUSION_MALLOC_TUNING=0`` turns it off.** It was opt-in for a day
because with it on 2 of 5 ``evaluate`` runs of the synthetic room gave a different
multi-view result in the fifth digit (fused 0.36033 against 0.36065). The allocator was not
the cause: the first parallel ``torch.sqrt`` of a process could run MKL VML's low-accuracy
kernel on one thread's half (a dispatch race in oneMKL 2024.2, pytorch/pytorch#188792, seen
with the tuning off too; the tuning only changed how often the threads collided), now
resolved up front by :mod:`.vml_warmup`; with that, five runs with the tuning and three
without gave the same numbers to the last digit. ``depth-fusion``
and every node's entry point call :func:`keep_freed_memory`; a ``MALLOC_MMAP_THRESHOLD_``
or ``MALLOC_TRIM_THRESHOLD_`` you set wins (then nothing is changed here), as does a
``MALLOC_ARENA_MAX`` for the arena cap.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform
import sys

log = logging.getLogger(__name__)

#: glibc's ``mallopt`` parameter numbers (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
#: Most malloc arenas: threads share them, so the kept peak is held at most this many times.
ARENA_MAX = 2
#: Allocations up to this come from the heap, not from fresh mmap pages: glibc's largest
#: allowed value on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``), above the 16 MiB chunk budget.
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory at the heap top is returned to the OS only above this.
TRIM_THRESHOLD = 1024 * 1024 * 1024
ENV_SWITCH = 'DEPTH_FUSION_MALLOC_TUNING'
USER_ENV = ('MALLOC_MMAP_THRESHOLD_', 'MALLOC_TRIM_THRESHOLD_')

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process; whether they are raised now.

    Both are needed: with only the mmap threshold raised the heap is trimmed after every
    large free, with only the trim threshold raised large blocks still go through mmap, and
    either alone faulted more than neither in a measurement here.
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get(ENV_SWITCH, '1') == '0':
        log.debug('allocator tuning off (%s=0)', ENV_SWITCH)
        return False
    if any(os.environ.get(name) for name in USER_ENV):
        log.debug('allocator tuning left to the environment (%s)', ', '.join(USER_ENV))
        return False
    mallopt = _glibc('mallopt', (ctypes.c_int, ctypes.c_int))
    if mallopt is None:
        return False
    arenas_ok = bool(os.environ.get('MALLOC_ARENA_MAX')) or bool(mallopt(M_ARENA_MAX, ARENA_MAX))
    mmap_ok = arenas_ok and bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    _applied = mmap_ok and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    log.debug('allocator tuning: %s', 'freed memory kept' if _applied else 'mallopt refused')
    return _applied


def release_free_memory() -> bool:
    """Hand the heap's free memory back to the OS now (glibc's ``malloc_trim``); whether it ran.

    For a bounded store that has just dropped much of what it held (map_node's kept keyframes,
    thinned with age): under the raised trim threshold above, the freed chunks would stay in
    the process, which then sat ~30 MB above the store's own cap. Rare (a thinning drops a
    quarter of the store), and a few milliseconds each."""
    trim = _glibc('malloc_trim', (ctypes.c_size_t,))
    if trim is None:
        return False
    trim(0)
    return True


def _glibc(name: str, argtypes: tuple) -> ctypes._CFuncPtr | None:
    """glibc's function ``name`` (returning int), or None on another C library or platform."""
    if not sys.platform.startswith('linux') or platform.libc_ver()[0] != 'glibc':
        return None
    try:
        function = getattr(ctypes.CDLL('libc.so.6'), name)
    except (OSError, AttributeError):
        return None
    function.argtypes = argtypes
    function.restype = ctypes.c_int
    return function
