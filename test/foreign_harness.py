"""A native kernel's calls recorded here and replayed on another CPU (aarch64, under qemu-user).

Why: the native kernels are built for ARM robot computers too (``native_build``), where the CI
cannot run them. A call is recorded on this machine, where the kernel is checked against its
torch twin: its scalar arguments and the bytes of every buffer before and after. The kernel's
source is then cross-compiled with a generated ``main`` that reads the buffers, makes the same
call and writes them back, and runs under ``qemu-aarch64``; every buffer must come back with
this machine's values (NaN for NaN: the two CPUs' default NaNs differ in their sign bit). A
buffer's type and length are not in the call (a pointer), so each kernel's test says them
(``buffers``: argument index to numpy dtype and element count, from the call's scalars).
"""

from __future__ import annotations

import ctypes
import math
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from depth_fusion_ros import native_build

#: The cross compiler and the emulator, and where the emulator finds the target's libraries.
CROSS_CC = 'aarch64-linux-gnu-gcc'
EMULATOR = 'qemu-aarch64'
SYSROOT = '/usr/aarch64-linux-gnu'

_C_TYPES = {
    ctypes.c_int64: 'int64_t',
    ctypes.c_int: 'int',
    ctypes.c_float: 'float',
    ctypes.c_double: 'double',
    ctypes.c_void_p: 'void *',
}


def missing_tools() -> str | None:
    """Why no call can be replayed here (no cross compiler or emulator), or None."""
    absent = [tool for tool in (CROSS_CC, EMULATOR) if shutil.which(tool) is None]
    if absent:
        return f'{" and ".join(absent)} not on the PATH (Debian: gcc-aarch64-linux-gnu, qemu-user)'
    return None


Buffers = Callable[[tuple], dict[int, tuple[type, int]]]


@dataclass
class Call:
    """One recorded call: the arguments, each buffer's type and its bytes before and after it."""

    args: tuple
    dtypes: dict[int, type]
    before: dict[int, bytes]
    after: dict[int, bytes]

    def same_values(self, index: int, other: bytes) -> bool:
        """Whether ``other`` holds buffer ``index``'s values after the call (NaN equal to NaN)."""
        mine = np.frombuffer(self.after[index], dtype=self.dtypes[index])
        theirs = np.frombuffer(other, dtype=self.dtypes[index])
        floating = np.issubdtype(mine.dtype, np.floating)
        return mine.shape == theirs.shape and bool(np.array_equal(mine, theirs, equal_nan=floating))


def record(monkeypatch, lib: ctypes.CDLL, name: str, buffers: Buffers) -> list[Call]:
    """Record every call of ``lib.name`` from now on (the call itself still runs)."""
    real = getattr(lib, name)
    calls: list[Call] = []

    def recording(*args):
        spans = {i: (d, n) for i, (d, n) in buffers(args).items() if args[i] is not None and n > 0}
        nbytes = {i: np.dtype(d).itemsize * n for i, (d, n) in spans.items()}
        before = {i: ctypes.string_at(args[i], n) for i, n in nbytes.items()}
        real(*args)
        after = {i: ctypes.string_at(args[i], n) for i, n in nbytes.items()}
        calls.append(Call(args, {i: d for i, (d, _) in spans.items()}, before, after))

    monkeypatch.setattr(lib, name, recording)
    return calls


def replay(source: Path, name: str, argtypes: list, call: Call, workdir: Path) -> dict[int, bytes]:
    """The buffers after ``call`` made by ``source`` built for aarch64 and run under the
    emulator (the plain kernels' flags, OpenMP on), by argument index."""
    spans = sorted(call.before)
    (workdir / 'in.bin').write_bytes(b''.join(call.before[i] for i in spans))
    values = []
    for i, (kind, value) in enumerate(zip(argtypes, call.args, strict=True)):
        values.append(f'buf[{spans.index(i)}]' if i in call.before else _literal(kind, value))
    prototype = ', '.join(_C_TYPES[kind] for kind in argtypes)
    sizes = ', '.join(str(len(call.before[i])) for i in spans) or '0'
    main = workdir / 'main.c'
    main.write_text(
        '#include <math.h>\n#include <stdint.h>\n#include <stdio.h>\n#include <stdlib.h>\n'
        f'void {name}({prototype});\n'
        f'static const size_t sizes[] = {{{sizes}}};\n'
        'int main(int argc, char **argv) {\n'
        f'    void *buf[{max(len(spans), 1)}];\n'
        '    FILE *in = fopen(argv[1], "rb"), *out = fopen(argv[2], "wb");\n'
        f'    for (int i = 0; i < {len(spans)}; i++) {{\n'
        '        buf[i] = malloc(sizes[i]);\n'
        '        if (fread(buf[i], 1, sizes[i], in) != sizes[i]) return 2;\n'
        '    }\n'
        f'    {name}({", ".join(values)});\n'
        f'    for (int i = 0; i < {len(spans)}; i++) fwrite(buf[i], 1, sizes[i], out);\n'
        '    return fclose(out);\n'
        '}\n'
    )
    flags = [f for f in native_build.BASE_FLAGS if f not in ('-shared', '-fPIC')]
    program = workdir / 'kernel'
    build = [CROSS_CC, *flags, '-o', str(program), str(main), str(source), '-lm']
    subprocess.run(build, check=True, timeout=120)
    out = workdir / 'out.bin'
    run = [EMULATOR, '-L', SYSROOT, str(program), str(workdir / 'in.bin'), str(out)]
    subprocess.run(run, check=True, timeout=300)
    data, after, at = out.read_bytes(), {}, 0
    for i in spans:
        after[i] = data[at : at + len(call.before[i])]
        at += len(call.before[i])
    return after


def _literal(kind, value) -> str:
    """A scalar argument as a C literal of its type (floats in hexadecimal: the exact value)."""
    if kind in (ctypes.c_float, ctypes.c_double):
        value = float(value)
        if not math.isfinite(value):
            return 'NAN' if math.isnan(value) else ('INFINITY' if value > 0 else '-INFINITY')
        return f'{value.hex()}f' if kind is ctypes.c_float else value.hex()
    if kind is ctypes.c_void_p:  # a None pointer (an optional buffer not given)
        return '0'
    return f'INT64_C({int(value)})' if kind is ctypes.c_int64 else str(int(value))
