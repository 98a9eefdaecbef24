"""A small C kernel of the package, compiled once per machine and loaded with ctypes.

Why ctypes and the system C compiler rather than a torch extension: the kernels are plain C
over raw float buffers (no torch headers, no pybind11, no ninja, nothing to pin), so building
one is a single ``cc`` call of well under a second, and a ctypes call releases the GIL (a
node's other threads run while a kernel does). The compiler is the one inductor already needs for
the compiled fusion kernels (``fusion/kernel_compile.py``); where there is none, or the CPU is
an x86-64 without AVX2 and FMA, :func:`load_native` says so once and returns ``None`` and the
caller keeps its torch code.

Every kernel is C (and OpenMP) that any C compiler builds for any CPU. On an x86-64 with AVX2
and FMA they are built with those (``-mavx2 -mfma``), and the two that work eight lanes at a
time (the matching cost, the frame descriptors) use the AVX2 intrinsics through
``multiview/simd8.h``; on another CPU (an ARM robot computer: Jetson, Raspberry Pi, RK3588) they
are built without the x86 flags and ``simd8.h`` gives the same operations as GCC vector
extensions (NEON there: two registers a vector, FMAs and floors as vector instructions). Every
number is the same on both: the only fused multiply-adds are written out (``fmaf``, or the FMA
intrinsic: one rounding wherever it runs), the compiler fuses none of its own
(``-ffp-contract=off``), and ``simd8.h`` keeps AVX2's rules where C has none. An x86-64 CPU
without AVX2 and FMA (before 2013-2015) runs the torch code: it would compute each written-out
FMA in software, three times slower than torch.

A library is cached under the user cache (``user_cache('native')``), named by a digest of its
source (with the package's own headers it includes, ``#include "name.h"`` beside it: kernels
share scalar helpers so), the compiler's version and the flags, written to a temporary name and renamed into
place, so that concurrent processes (the nodes of one graph) never load a half-written file
and a changed source or compiler builds anew; a build deletes the libraries nobody loaded
for 60 days (``cache_prune.py``). ``DEPTH_FUSION_NATIVE=0`` in the environment
turns every native kernel off (the torch code runs; for comparisons), and
``DEPTH_FUSION_NATIVE=portable`` builds them as an ARM machine does, without the x86 flags
(the vector extensions' code, to test its numbers on an x86-64 machine, where its FMAs run in
software: slow).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import logging
import os
import platform
import re
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

from .build_env import cpu_flags, switched_on
from .cache_prune import prune_unused
from .user_cache import user_cache

log = logging.getLogger(__name__)

#: What the x86-64 kernels are written for (AVX2 and FMA: every x86-64 CPU since 2013-2015).
X86_FLAGS = ('-mavx2', '-mfma')
#: ``DEPTH_FUSION_NATIVE`` set to this: the kernels built without the x86 flags.
PORTABLE = 'portable'
#: No contraction beyond the FMAs written out: the kernels reproduce torch's numbers. OpenMP:
#: the library needs ``libgomp.so.1``, which resolves to the copy torch has loaded (the same
#: runtime and thread team as torch's own parallel loops; two would spin against each other).
BASE_FLAGS = ('-O3', '-std=c11', '-fPIC', '-shared', '-fopenmp', '-ffp-contract=off', '-fno-math-errno')

_lock = threading.Lock()
_loaded: dict[str, ctypes.CDLL | None] = {}


def native_enabled() -> bool:
    """False when ``DEPTH_FUSION_NATIVE`` is ``0`` (or ``false``/``no``/``off``)."""
    return switched_on('DEPTH_FUSION_NATIVE')


def portable_only() -> bool:
    """Whether ``DEPTH_FUSION_NATIVE`` is ``portable``: the kernels built as on a machine
    without AVX2 (an ARM board), whatever this CPU has."""
    return os.environ.get('DEPTH_FUSION_NATIVE', '').strip().lower() == PORTABLE


def kernel_threads(work: int, minimum: int) -> int:
    """OpenMP threads for one kernel call of ``work`` items: torch's thread count (the kernels'
    parallel loops run on torch's own thread team), or 1 below ``minimum`` items, where handing
    the work over costs more than it saves. Each item is computed alone, so the numbers do not
    depend on the split."""
    import torch  # here: building a kernel needs no torch, a call does

    return max(1, torch.get_num_threads()) if work >= minimum else 1


def load_native(source: Path, signatures: dict[str, list[type]]) -> ctypes.CDLL | None:
    """The library built from the C file ``source`` (built on first use) with its functions'
    argument types set from ``signatures`` (each returns nothing), or ``None`` where it cannot
    run here; the reason is logged once per source and process."""
    key = str(source)
    with _lock:
        if key not in _loaded:
            lib = _build_and_load(source)
            for name, argtypes in signatures.items() if lib is not None else ():
                function = getattr(lib, name)
                function.argtypes, function.restype = argtypes, None
            _loaded[key] = lib
        return _loaded[key]


def _build_and_load(source: Path) -> ctypes.CDLL | None:
    why = unavailable()
    if why is not None:  # this machine: said, not a fault
        log.info('native kernel %s not used: %s; the torch code runs instead', source.name, why)
        return None
    try:
        return ctypes.CDLL(str(_built(source)))
    except (OSError, subprocess.SubprocessError) as exc:  # it should have built here: a fault to see
        log.warning('native kernel %s not built (%s); the torch code runs instead', source.name, _reason(exc))
        return None


def _reason(exc: BaseException) -> str:
    """One line of a failed build: the compiler's first error line (its last line is often a
    caret under the source), else the last line, else the exception's name."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip()]
    errors = [line for line in lines if 'error' in line.lower()]
    return (errors or lines[-1:] or [repr(exc)])[0]


def unavailable() -> str | None:
    """Why the native kernels cannot run on this machine (``load_native`` logs it once a kernel,
    ``depth-fusion kernels`` says it), or None where they can."""
    if not native_enabled():
        return 'DEPTH_FUSION_NATIVE=0'
    if _x86() and not portable_only():
        flags = cpu_flags()
        if flags is not None and not {'avx2', 'fma'} <= flags:
            return "the CPU has no AVX2 and FMA (the kernels' FMAs would run in software, slower than torch)"
    if _compiler() is None:
        return 'no C compiler (cc, gcc or $CC) on the PATH'
    return None


def _x86() -> bool:
    return platform.machine().lower() in ('x86_64', 'amd64')


def build_target() -> str:
    """What the kernels are built for here, in words (``depth-fusion kernels`` says it)."""
    if machine_flags():
        return 'x86-64 with AVX2 and FMA'
    return f'{platform.machine() or "this CPU"} without x86 flags (simd8.h as vector extensions)'


def machine_flags() -> tuple[str, ...]:
    """The x86 flags on an x86-64 (which runs the kernels only with AVX2 and FMA: their eight
    lanes are then AVX2 registers), none on another CPU or with ``DEPTH_FUSION_NATIVE=portable``."""
    return X86_FLAGS if _x86() and not portable_only() else ()


def _compiler() -> str | None:
    for name in (os.environ.get('CC'), 'cc', 'gcc'):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


@functools.cache
def _compiler_version(cc: str) -> str:
    """``cc --version``: part of every library's name (asked once per process, not per kernel)."""
    return subprocess.run([cc, '--version'], capture_output=True, text=True, check=True, timeout=30).stdout


def _built(source: Path) -> Path:
    """The cached library of ``source``, compiled now if it is not there yet; without OpenMP
    (one thread: the pragmas are ignored) where the compiler has none."""
    cc = _compiler()
    assert cc is not None
    version = _compiler_version(cc)
    failure: subprocess.SubprocessError | None = None
    machine = machine_flags()
    for flags in ([*BASE_FLAGS, *machine], [f for f in (*BASE_FLAGS, *machine) if f != '-fopenmp']):
        try:
            return _built_with(source, cc, version, flags)
        except subprocess.SubprocessError as exc:
            failure = failure or exc
    assert failure is not None
    raise failure


def _source_text(source: Path) -> bytes:
    """The C file's bytes and those of every local header it includes (``#include "name"``,
    resolved beside it, as the compiler does): a changed header names a new library."""
    text = source.read_bytes()
    headers = re.findall(rb'^\s*#\s*include\s+"([^"]+)"', text, flags=re.MULTILINE)
    return b'\0'.join([text, *((source.parent / h.decode()).read_bytes() for h in headers)])


def _built_with(source: Path, cc: str, version: str, flags: list[str]) -> Path:
    digest = hashlib.sha256(b'\0'.join([_source_text(source), version.encode(), ' '.join(flags).encode()]))
    out = user_cache('native') / f'{source.stem}-{digest.hexdigest()[:16]}.so'
    if out.exists():
        with contextlib.suppress(OSError):  # marked used (cache_prune); a read-only cache stays as it is
            os.utime(out)
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{source.stem}-', suffix='.so', dir=out.parent)
    os.close(fd)
    try:
        command = [cc, *flags, '-o', tmp, str(source), '-lm']
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            raise subprocess.SubprocessError(done.stderr.strip() or f'{cc} exited with {done.returncode}')
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    how = '' if '-fopenmp' in flags else ' without OpenMP (one thread)'
    log.info('native kernel %s built%s: %s', source.name, how, out)
    prune_unused(out.parent, '*.so', keep=[out])
    return out
