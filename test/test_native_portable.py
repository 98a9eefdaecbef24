"""The native kernels as a CPU without AVX2 builds them (an ARM robot computer, an old x86-64),
here with ``DEPTH_FUSION_NATIVE=portable``: every kernel built without the x86 flags, so that
``multiview/simd8.h`` gives its eight lanes as GCC vector extensions instead of AVX2 intrinsics.
The native kernels' own tests pass on that build, and it gives the AVX2 build's numbers bit for
bit on a filter stream, the halo test and the guard's medians (the aarch64 builds themselves:
test_native_aarch64.py).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from native_calls import filter_end_state

import depth_fusion_ros
from depth_fusion_ros import build_env, native_build, native_kernels
from depth_fusion_ros.fusion import neighbour_median, occlusion
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe

pytestmark = pytest.mark.usefixtures('one_torch_thread')

SOURCES = sorted(Path(depth_fusion_ros.__file__).parent.rglob('*.c'))
HERE = Path(__file__).parent
#: The native kernels' own tests (each against its torch, numpy or OpenCV twin).
#: (Not this file, nor the aarch64 replays, which need tools the CI lacks.)
NATIVE_TESTS = sorted(
    p.name
    for p in HERE.glob('test_native_*.py')
    if p.name not in ('test_native_portable.py', 'test_native_aarch64.py')
)


def _compiler_or_skip() -> None:
    if native_build._compiler() is None:
        pytest.skip('no C compiler here')


def test_portable_builds_every_kernel_without_the_x86_flags(monkeypatch, tmp_path):
    _compiler_or_skip()
    log = tmp_path / 'cc.log'
    cc = tmp_path / 'cc'
    cc.write_text(f'#!/bin/sh\necho "$@" >> {log}\nexec {native_build._compiler()} "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv('CC', str(cc))
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    monkeypatch.setenv('DEPTH_FUSION_NATIVE', 'portable')
    monkeypatch.setattr(native_build, '_loaded', {})
    assert native_build.machine_flags() == ()
    for source in SOURCES:
        assert native_build.load_native(source, {}) is not None, source.name
    commands = [line for line in log.read_text().splitlines() if ' -o ' in line]  # not --version
    assert len(commands) == len(SOURCES) == len(native_kernels.KERNELS) == 8
    assert not any(flag in command for command in commands for flag in native_build.X86_FLAGS)


def test_the_native_tests_pass_on_the_portable_build(tmp_path):
    """Every native kernel's tests (bit for bit against torch, numpy and OpenCV where they
    say so) on the vector extensions' code, none skipped."""
    _compiler_or_skip()
    env = {**os.environ, 'DEPTH_FUSION_NATIVE': 'portable', 'XDG_CACHE_HOME': str(tmp_path / 'cache')}
    command = [sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', *NATIVE_TESTS]
    done = subprocess.run(command, cwd=HERE, env=env, capture_output=True, text=True, timeout=600)
    summary = done.stdout.strip().splitlines()[-1]
    assert done.returncode == 0, done.stdout[-3000:]
    assert ' passed' in summary and 'skipped' not in summary and 'failed' not in summary, summary


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a.numpy() if isinstance(a, torch.Tensor) else a).tobytes())
    return h.hexdigest()


def _filter_and_fusion_tests() -> tuple[str, str, str]:
    """The filter's end state on a synthetic room, the halo test's points and the guard's
    neighbour medians on a rendered keyframe, each as a digest."""
    state = _digest(*filter_end_state(8).values())
    image, single, m, points = rendered_halo_keyframe(width=160, height=120, point_share=0.6)
    halo = occlusion.halo_points(image, single, m, points)
    rows, cols = np.nonzero(points)
    values = np.log(m[rows, cols]).astype(np.float64)
    median = neighbour_median.nearest_median(cols, rows, values, radius=12.0, max_neighbours=8)
    return state, _digest(halo), _digest(*median)


def test_the_portable_build_gives_the_avx2_builds_numbers(monkeypatch, tmp_path):
    """A filter stream (its descriptors, searches, choice of rows, bracket and update), the
    halo test and the guard's medians: the same bits from both builds of every kernel."""
    _compiler_or_skip()
    if native_build.machine_flags() != native_build.X86_FLAGS:
        pytest.skip('not an x86-64 CPU with AVX2 and FMA: only the portable build runs here')
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    results = {}
    for mode in ('1', 'portable'):
        monkeypatch.setenv('DEPTH_FUSION_NATIVE', mode)
        monkeypatch.setattr(native_build, '_loaded', {})
        assert native_kernels.prepare() == len(native_kernels.KERNELS), mode
        results[mode] = _filter_and_fusion_tests()
    assert results['portable'] == results['1']


def test_where_the_kernels_run_and_how_they_are_built(monkeypatch):
    """An ARM machine builds them without the x86 flags; an x86-64 with AVX2 and FMA with them;
    one without runs torch (its FMAs in software would be slower), said in one line."""
    _compiler_or_skip()
    monkeypatch.delenv('DEPTH_FUSION_NATIVE', raising=False)
    monkeypatch.setattr(native_build.platform, 'machine', lambda: 'aarch64')
    assert native_build.unavailable() is None
    assert native_build.machine_flags() == ()
    monkeypatch.setattr(native_build.platform, 'machine', lambda: 'x86_64')
    monkeypatch.setattr(native_build, 'cpu_flags', lambda: {'sse2', 'avx2', 'fma'})
    assert native_build.unavailable() is None
    assert native_build.machine_flags() == native_build.X86_FLAGS
    monkeypatch.setattr(native_build, 'cpu_flags', lambda: {'sse2', 'avx'})
    assert 'no AVX2 and FMA' in native_build.unavailable()
    monkeypatch.setenv('DEPTH_FUSION_NATIVE', 'portable')  # the tests' way to build the ARM code here
    assert native_build.unavailable() is None
    assert native_build.machine_flags() == ()


def test_the_cpus_features_are_read_on_x86_and_on_arm():
    """The kernels' cache keys and the x86 check read the CPU's features: an x86-64's ``flags``
    line, an ARM board's ``Features`` line (before, an ARM board's were not read at all)."""
    x86 = 'processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: fpu sse2 avx2 fma\nbugs\t\t: none\n'
    arm = 'processor\t: 0\nBogoMIPS\t: 62.50\nFeatures\t: fp asimd evtstrm crc32 atomics\nCPU part\t: 0xd42\n'
    assert build_env.flags_line(x86) == 'flags\t\t: fpu sse2 avx2 fma'
    assert build_env.flags_line(arm) == 'Features\t: fp asimd evtstrm crc32 atomics'
    assert build_env.flags_line('processor\t: 0\n') is None


def test_the_kernels_command_says_why_none_run(monkeypatch, capsys):
    """``depth-fusion kernels`` on a machine where the C kernels cannot run says why in its
    native line (here: switched off), and goes on with the fusion's kernels."""
    from depth_fusion_ros.cli import kernels

    monkeypatch.setenv('DEPTH_FUSION_NATIVE', '0')
    assert kernels._native_line() == (
        'native C kernels: not used here (DEPTH_FUSION_NATIVE=0); their torch and numpy twins run'
    )
    monkeypatch.setenv('DEPTH_FUSION_NATIVE', 'portable')
    monkeypatch.setattr(native_build.platform, 'machine', lambda: 'aarch64')
    assert native_build.build_target() == 'aarch64 without x86 flags (simd8.h as vector extensions)'
