"""The fusion kernels compiled ahead of time (AOTInductor), kept on disk, loaded in milliseconds.

Why: ``torch.compile`` traces the kernels again in every process, with or without its own
disk cache: a fusion node is warm 5.5-9 s after it starts on 2 cores, and until then it fuses
with the eager kernels (~5.7x slower), so a live camera that starts with the node falls behind
(docs/performance.md, "Live from an independent client"). ``torch.export`` plus AOTInductor
turns the same functions into a shared library once (``depth-fusion kernels``, ~20-40 s on 2
cores); every process after that loads it in a few milliseconds and runs the same generated
loops (the same numbers to float rounding: ``test/test_fusion_aot.py``).

Only the package's model library is kept, and called through ctypes. It is specific to the
torch version, the device type, the CPU's feature flags, the weight parameters and the
kernels' source, all in its file name, so a changed setting or a new release simply misses
the cache and the node compiles as before. CPU only: the CUDA path
keeps ``torch.compile`` (not measured with AOTInductor). ``DEPTH_FUSION_AOT=0`` ignores the
cache.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import hashlib
import logging
import os
import platform
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

try:
    import fcntl
except ImportError:  # not POSIX: builds are not serialised (each builds; the rename keeps files whole)
    fcntl = None  # type: ignore[assignment]

from ..build_env import cpu_flags_line, switched_on
from ..cache_prune import UNUSED_DAYS, prune_unused
from ..user_cache import user_cache
from . import chunk_sums, interpolation, kernel_compile, weights
from .weights import Samples, WeightParams

log = logging.getLogger(__name__)

KERNELS = ('sums', 'blend')
ENV_SWITCH = 'DEPTH_FUSION_AOT'
#: Dynamic sizes the packages accept (pixels per chunk, points of Ω, pixels of a keyframe).
_MAX_SIZE = 1 << 24


def cache_dir() -> Path:
    return user_cache('aot')


def enabled(device: torch.device) -> bool:
    return device.type == 'cpu' and switched_on(ENV_SWITCH)


def _cpu_flags() -> str:
    return cpu_flags_line() or platform.processor() or platform.machine()


@functools.cache
def _source_digest() -> str:
    digest = hashlib.sha256()
    for module in (chunk_sums, interpolation, weights):
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()


def package_path(name: str, params: WeightParams, device: torch.device) -> Path:
    """Where the model library of kernel ``name`` for these parameters lives (built or not).

    The structure scale is not part of it: the interpolation divides the depths by it before
    the kernels see them (``interpolation.interpolate``), so every scale shares one build.
    """
    digest = hashlib.sha256()
    for part in (
        torch.__version__,
        name,
        repr(dataclasses.replace(params, structure_scale=1.0)),
        device.type,
        _cpu_flags(),
        _source_digest(),
        # the options as written, not as this torch filters them: no inductor import on a lookup
        repr(sorted(kernel_compile.INDUCTOR_OPTIONS.items())),
        repr(sorted(kernel_compile.CPU_INDUCTOR_OPTIONS.items())) if device.type == 'cpu' else '',
    ):
        digest.update(str(part).encode())
    return cache_dir() / f'fusion_{name}_{digest.hexdigest()[:20]}.so'


def _sums_module(params: WeightParams) -> torch.nn.Module:
    class Sums(torch.nn.Module):
        def forward(self, px, py, ps, pgx, pgy, qx, qy, qs, qgx, qgy, v, lw):
            p, q = Samples(px, py, ps, pgx, pgy), Samples(qx, qy, qs, qgx, qgy)
            return chunk_sums.chunk_sums_one_pass(p, q, v, lw, params)

    return Sums()


def _blend_module(params: WeightParams) -> torch.nn.Module:
    class Blend(torch.nn.Module):
        def forward(self, zero, ps, pgx, pgy, cs, cgx, cgy, dx, dy, bilinear, offset, support):
            pixels, corners = Samples(zero, zero, ps, pgx, pgy), Samples(zero, zero, cs, cgx, cgy)
            return interpolation._blend_corners(pixels, corners, dx, dy, bilinear, offset, support, params)

    return Blend()


def _examples(name: str) -> tuple[tuple[torch.Tensor, ...], tuple[dict[int, object], ...]]:
    """Example inputs (sizes above 1, so export keeps them dynamic) and their dynamic dims."""
    g = torch.Generator().manual_seed(0)
    rand = lambda *shape: torch.rand(*shape, generator=g) + 0.5  # noqa: E731
    if name == 'sums':
        c, q = (
            torch.export.Dim('pixels', min=2, max=_MAX_SIZE),
            torch.export.Dim('points', min=2, max=_MAX_SIZE),
        )
        args = (*(rand(64, 1) for _ in range(5)), *(rand(1, 32) for _ in range(5)), rand(32), -rand(1, 32))
        return args, (*([{0: c}] * 5), *([{1: q}] * 5), {0: q}, {1: q})
    n = torch.export.Dim('pixels', min=2, max=_MAX_SIZE)
    args = (torch.zeros(1, 1), *(rand(64, 1) for _ in range(3)), *(rand(64, 4) for _ in range(8)))
    return args, ({}, *([{0: n}] * 3), *([{0: n}] * 8))


def build(params: WeightParams, device: torch.device | str = 'cpu') -> dict[str, float]:
    """Compile both kernels for ``params`` into the cache; returns the seconds each took."""
    device = torch.device(device)
    if device.type != 'cpu':
        raise ValueError(f'ahead-of-time fusion kernels are built for the CPU only, not {device}')
    modules = {'sums': _sums_module(params), 'blend': _blend_module(params)}
    seconds, built = {}, []
    for name in KERNELS:
        start = time.perf_counter()
        args, dynamic = _examples(name)
        program = torch.export.export(modules[name], args, dynamic_shapes=dynamic)
        target = package_path(name, params, device)
        target.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=target.parent) as work:
            package = torch._inductor.aoti_compile_and_package(
                program,
                package_path=str(Path(work) / 'kernel.pt2'),
                inductor_configs=kernel_compile.inductor_options(device),
            )
            _take_library(Path(package), target)
        built.append(target)
        seconds[name] = time.perf_counter() - start
        log.info('AOT fusion kernel %s built in %.1f s: %s', name, seconds[name], target)
    forget_loaded()
    removed = prune_unused(cache_dir(), 'fusion_*.so', keep=built)
    if removed:
        log.info('removed %d fusion kernel file(s) not loaded for %d days', len(removed), UNUSED_DAYS)
    return seconds


@contextlib.contextmanager
def build_lock(wait: bool) -> Iterator[bool]:
    """The cache's build lock (an advisory ``flock`` on ``cache_dir()/build.lock``): yields
    whether this process holds it. Two builders of the same kernels (``depth-fusion kernels``
    and a fusion node's background build, or two nodes) would each spend ~45 s of CPU on the
    same files; with the lock the second waits (``wait``) or gives up. The kernel files are
    renamed into place, so a loader never needs the lock."""
    path = cache_dir() / 'build.lock'
    path.parent.mkdir(parents=True, exist_ok=True)
    if fcntl is None:
        yield True
        return
    with open(path, 'a+') as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def build_if_missing(params: WeightParams, wait: bool = True) -> dict[str, float] | None:
    """:func:`build` under :func:`build_lock`, only when the kernels are not in the cache once
    the lock is held (another builder may just have made them): the seconds each took, ``{}``
    when nothing was missing, None when another process holds the lock and ``wait`` is False."""
    with build_lock(wait) as held:
        if not held:
            return None
        if available(params, 'cpu'):
            return {}
        return build(params, 'cpu')


def available(params: WeightParams, device: torch.device | str = 'cpu') -> bool:
    """Whether every kernel of ``params`` is built (then a node is warm when it starts)."""
    device = torch.device(device)
    return enabled(device) and all(package_path(n, params, device).exists() for n in KERNELS)


#: Kernels loaded, by (name, parameters, device type, cache directory); None for a file that
#: would not load. A kernel not built is not remembered: a build in another process (a fusion
#: node's background builder) is found at the next lookup.
_loaded: dict[tuple[str, WeightParams, str, str], Callable | None] = {}


def forget_loaded() -> None:
    """Look every kernel up again (after a build here, or a file replaced)."""
    _loaded.clear()


def _load(name: str, params: WeightParams, device_type: str) -> Callable | None:
    key = (name, params, device_type, str(cache_dir()))
    if key in _loaded:
        return _loaded[key]
    path = package_path(name, params, torch.device(device_type))
    if not path.exists():
        return None
    try:
        runner = _ctypes_runner(path)
    except Exception as exc:  # a broken or foreign file: compile as if there were none
        log.warning('ignoring the AOT fusion kernel %s (%s)', path, exc)
        runner = None
    else:
        with contextlib.suppress(OSError):  # marked used (prune_unused); a read-only cache stays as it is
            os.utime(path)
    _loaded[key] = runner
    return runner


def _take_library(package: Path, target: Path) -> None:
    """The package's one model library, the only part the runner needs, moved to ``target``
    (renamed into place: a process loading meanwhile never sees half a file)."""
    with zipfile.ZipFile(package) as archive:
        names = [n for n in archive.namelist() if n.endswith('.so')]
        if len(names) != 1:
            raise ValueError(f'{package}: {len(names)} shared libraries in the package, expected 1')
        staged = package.with_suffix('.so')
        staged.write_bytes(archive.read(names[0]))
    os.replace(staged, target)


def _ctypes_runner(path: Path) -> Callable:
    """``AOTInductorModelContainerRun`` of the model library (aoti_runtime/interface.h), called
    through ctypes, which lets go of the GIL for the call: the composed graph's other nodes run
    meanwhile (torch's own pybind runner holds it for the whole 40-100 ms). Input handles are
    given up to the call, output handles taken back as tensors."""
    aoti = torch._C._aoti
    handle_type = ctypes.c_void_p
    capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    capsule_pointer.restype, capsule_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    capsule = ctypes.pythonapi.PyCapsule_New
    capsule.restype, capsule.argtypes = ctypes.py_object, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
    lib = ctypes.CDLL(str(path))
    create = lib.AOTInductorModelContainerCreateWithDevice
    create.restype = ctypes.c_int32
    create.argtypes = [ctypes.POINTER(handle_type), ctypes.c_size_t, ctypes.c_char_p, ctypes.c_char_p]
    count = lib.AOTInductorModelContainerGetNumOutputs
    count.restype, count.argtypes = ctypes.c_int32, [handle_type, ctypes.POINTER(ctypes.c_size_t)]
    run = lib.AOTInductorModelContainerRun
    run.restype = ctypes.c_int32
    run.argtypes = [handle_type, ctypes.POINTER(handle_type), ctypes.c_size_t]
    run.argtypes += [ctypes.POINTER(handle_type), ctypes.c_size_t, handle_type, handle_type]
    container, outputs = handle_type(), ctypes.c_size_t()
    if create(ctypes.byref(container), 1, b'cpu', None) != 0 or count(container, ctypes.byref(outputs)) != 0:
        raise RuntimeError('the model container could not be created')
    n_out = outputs.value

    def call(*tensors: torch.Tensor) -> list[torch.Tensor]:
        dense = [t.contiguous() for t in tensors]  # the generated loops index the example's layout
        handles = [capsule_pointer(c, None) for c in aoti.unsafe_alloc_void_ptrs_from_tensors(dense)]
        out = (handle_type * n_out)()
        if run(container, (handle_type * len(handles))(*handles), len(handles), out, n_out, None, None) != 0:
            raise RuntimeError(f'{path.name}: the model run failed')
        return aoti.alloc_tensors_by_stealing_from_void_ptrs(
            [capsule(out[i], None, None) for i in range(n_out)]
        )

    call.container = container  # type: ignore[attr-defined]  (kept alive with the function)
    return call


def kernel(name: str, params: WeightParams, device: torch.device) -> Callable | None:
    """The loaded kernel ``name`` with the call signature of its ``interpolation`` function
    (without ``params``), or None when it is not built or not used here."""
    if not enabled(device):
        return None
    loaded = _load(name, params, device.type)
    if loaded is None:
        return None
    if name == 'sums':

        def sums(
            p: Samples, q: Samples, v: torch.Tensor, lw: torch.Tensor | None
        ) -> tuple[torch.Tensor, ...]:
            # One point is a size the package does not take: two passes. (One pixel never comes:
            # interpolation._offsets_at pads a call to MIN_KERNEL_ROWS.)
            if q.x.shape[-1] < 2:
                return chunk_sums.no_one_pass()
            lw = torch.zeros_like(q.x) if lw is None else lw  # + 0 leaves every exponent as it was
            return tuple(loaded(*p, *q, v, lw))

        return sums

    def blend(
        pixels: Samples, corners: Samples, dx: torch.Tensor, dy: torch.Tensor, *rest: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        return tuple(
            loaded(pixels.x, pixels.s, pixels.gx, pixels.gy, corners.s, corners.gx, corners.gy, dx, dy, *rest)
        )

    return blend
