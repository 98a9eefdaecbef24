"""How the fusion kernels are compiled, and what runs when compiling fails.

The kernels (:mod:`.chunk_sums`' one-pass sums, the fast mode's corner blend) are plain torch
functions. Here they become fused loops: the library built ahead of time when there is one
(:mod:`.aot_kernels`, ``depth-fusion kernels``), else ``torch.compile`` in this process with
the inductor settings below (which the ahead-of-time build uses too). A compiler that fails
(no C++ toolchain, an unsupported platform) is logged once per device type, and the eager
form runs from then on: the same numbers, only slower.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

from ..compile_lock import COMPILE_LOCK, compile_serialised
from .weights import WeightParams

log = logging.getLogger(__name__)

#: Compiled kernels of this process, by (name, parameters, device type).
COMPILED: dict[tuple, Callable] = {}
#: Device types whose compiler failed once: eager from then on.
COMPILE_FAILED: set[str] = set()

#: Inductor settings of the fusion kernels. C++ (CPU): contract ``a * b + c`` into fused
#: multiply-adds (inductor's default is ``-ffp-contract=off``; every polynomial step and sum
#: becomes one instruction, rounded once: as accurate or more; 1.3x faster). Both backends:
#: never split the one-pass loop by materialising an intermediate of size (pixels, Ω), which
#: inductor does by default for an expression read more than 4 times (the weight is read
#: by the five sums: three loops and two 64 MB buffers per chunk instead of one loop).
#: C++: the loops' thread count is the caller's at run time (``#pragma omp parallel`` without
#: ``num_threads``; torch's OpenMP runtime, which ``torch.set_num_threads`` sets), not the
#: builder's: without it a build in a one-thread process (a fusion node's background builder,
#: ``OMP_NUM_THREADS=1``) emitted no parallel loop at all, and every process that loaded that
#: library fused on one core (exact 0.167 s at 2 threads against 0.089 s; docs/performance.md).
INDUCTOR_OPTIONS = {
    'cpp.enable_floating_point_contract_flag': 'fast',
    'realize_reads_threshold': 1 << 20,
    'cpp.dynamic_threads': True,
}

#: On a CPU the kernel is called through inductor's C++ wrapper: the default Python wrapper's
#: binding holds the GIL while the C++ loop runs (40-95 ms a keyframe), so in the composed graph
#: every other node's Python waited for it; the C++ wrapper releases it around the call. Measured
#: (docs/performance.md, 2026-11-27): composed paced median latency 480-510 -> 434-440 ms, the
#: multi-view node's mean 217-222 -> 121-138 ms; the same offsets bit for bit; the compile about
#: as long (``warm_up`` with an empty cache 15.5 against 14.6 s on 2 cores, a warm one 4.8 / 4.7 s).
CPU_INDUCTOR_OPTIONS = {'cpp_wrapper': True}


def inductor_options(device: torch.device) -> dict[str, object]:
    """The :data:`INDUCTOR_OPTIONS` (and on a CPU :data:`CPU_INDUCTOR_OPTIONS`) this torch
    knows (names move between releases; an unknown one would make ``torch.compile`` raise).
    Imports the compiler, so holding ``COMPILE_LOCK`` (compile_lock.py)."""
    try:
        with COMPILE_LOCK:
            import torch._inductor.config as inductor_config

            known = inductor_config.get_config_copy()
    except Exception:  # no inductor at all: compiling fails later (logged) and falls back to eager
        return {}
    options = dict(INDUCTOR_OPTIONS)
    if device.type == 'cpu':
        options.update(CPU_INDUCTOR_OPTIONS)
    return {name: value for name, value in options.items() if name in known}


def kernel_source(params: WeightParams, device: torch.device | str) -> str:
    """What :func:`maybe_compiled` gives the kernels of ``params`` on ``device`` now, in words:
    the library built ahead of time (threads sized by the caller), ``torch.compile`` in this
    process, or eager code after a failed compile. Their speeds differ several times, so a
    figure taken with them says which (``bench --only fusion``)."""
    from . import aot_kernels

    dev = torch.device(device)
    if dev.type in COMPILE_FAILED:
        return 'eager: the compiler failed (logged above)'
    if aot_kernels.available(params, dev):
        return f'kernels built ahead of time ({aot_kernels.cache_dir()})'
    return 'kernels compiled by torch.compile in this process'


def maybe_compiled(
    name: str,
    fn: Callable,
    params: WeightParams,
    compile_kernel: bool,
    device: torch.device,
    fallback: Callable | None = None,
) -> Callable:
    """``fn(*args, params)`` as a function of ``args``, compiled with ``torch.compile``
    (inductor) when asked and possible.

    Compiling fuses the elementwise passes into one loop (several times faster on CPU than
    eager). A failing compiler (no C++ toolchain, unsupported platform) is logged once and
    eager code is used from then on: same numbers, only slower. ``fallback(*args)`` replaces
    the eager ``fn`` after a failure when given (a kernel whose eager form would not bound
    its memory).
    """

    def eager(*args: object) -> tuple[torch.Tensor, ...]:
        return fn(*args, params)

    if not compile_kernel or device.type in COMPILE_FAILED:
        return eager
    from . import aot_kernels  # a package built ahead of time (depth-fusion kernels) needs no compile

    compiled = aot_kernels.kernel(name, params, device)
    what = (
        'the ahead-of-time fusion kernels' if compiled is not None else 'torch.compile of the fusion kernels'
    )
    if compiled is None:
        key = (name, params, device.type)
        if key not in COMPILED:
            # Serialised: a compile session flips a process-wide flag other threads read, and the
            # compiler's first import must not race another thread's (compile_lock.py).
            COMPILED[key] = compile_serialised(eager, dynamic=True, options=inductor_options(device))
        compiled = COMPILED[key]

    backup = fallback or eager

    def guarded(*args: object) -> tuple[torch.Tensor, ...]:
        if device.type in COMPILE_FAILED:
            return backup(*args)
        try:
            return compiled(*args)
        except Exception as exc:  # the compiler stack raises many types; any failure means eager
            COMPILE_FAILED.add(device.type)
            log.warning('%s failed on %s (%s); using eager', what, device, exc)
            return backup(*args)

    return guarded
