"""What a kernel the package builds on this machine depends on: the CPU's flags and the switches.

Two kinds of kernel library are built into the user cache: the AOT fusion kernels
(``fusion/aot_kernels.py``, keyed by the CPU's flags because inductor compiles for this CPU)
and the native C kernels (``native_build.py``, which need AVX2 and FMA). Both read the flags
from here, and each has an environment switch that turns it off for comparisons, read the
same way.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path


@functools.cache
def cpu_flags_line() -> str | None:
    """The feature line of /proc/cpuinfo (its first CPU), or None where it cannot be read."""
    try:
        return flags_line(Path('/proc/cpuinfo').read_text())
    except OSError:
        return None


def flags_line(cpuinfo: str) -> str | None:
    """The first feature line of a /proc/cpuinfo text: ``flags`` on an x86-64 (``avx2``,
    ``fma``, ...), ``Features`` on an ARM board (``asimd``, ``sve``, ...); None without one."""
    for line in cpuinfo.splitlines():
        if line.startswith(('flags', 'Features')) and ':' in line:
            return line
    return None


def cpu_flags() -> set[str] | None:
    """The CPU's feature flags (``avx2``, ``fma``, ...; an ARM board's ``asimd``, ...), or None
    where they cannot be read."""
    line = cpu_flags_line()
    return None if line is None else set(line.split(':', 1)[1].split())


def switched_on(variable: str) -> bool:
    """False when the environment ``variable`` is ``0``, ``false``, ``no`` or ``off``; true
    when it is unset or anything else."""
    return os.environ.get(variable, '1').strip().lower() not in ('0', 'false', 'no', 'off')
