"""The native kernels on a CPU without AVX2 (an ARM robot computer), as
``DEPTH_FUSION_NATIVE=portable`` builds them here: the plain C kernels without the x86 flags,
the two written with AVX2 intrinsics left to torch and OpenCV, and the filter and the fusion's
tests then giving what torch gives with every kernel off, bit for bit (the aarch64 builds
themselves: test_native_aarch64.py).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

import depth_fusion_ros
from depth_fusion_ros import native_build
from depth_fusion_ros.fusion import native_halo, neighbour_median, occlusion
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe
from depth_fusion_ros.multiview import native_cost, native_filter, native_scores

pytestmark = pytest.mark.usefixtures('one_torch_thread')

SOURCES = sorted(Path(depth_fusion_ros.__file__).parent.rglob('*.c'))
#: The kernels written with x86-64 SIMD intrinsics; every other one is plain C.
X86_SIMD = {'matching_cost.c', 'describe_table.c'}


def _compiler_or_skip() -> None:
    if native_build._compiler() is None:
        pytest.skip('no C compiler here')


def test_every_kernel_but_two_is_plain_c():
    assert {s.name for s in SOURCES if native_build.needs_x86_simd(s)} == X86_SIMD
    assert len(SOURCES) - len(X86_SIMD) == 6


def test_portable_builds_the_plain_kernels_without_the_x86_flags(monkeypatch, tmp_path):
    """What an ARM machine gets: each plain kernel built with no x86 flag and loaded; the two
    others declined with a reason that names them, and no library built for them."""
    _compiler_or_skip()
    log = tmp_path / 'cc.log'
    cc = tmp_path / 'cc'
    cc.write_text(f'#!/bin/sh\necho "$@" >> {log}\nexec {native_build._compiler()} "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv('CC', str(cc))
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    monkeypatch.setenv('DEPTH_FUSION_NATIVE', 'portable')
    monkeypatch.setattr(native_build, '_loaded', {})
    for source in SOURCES:
        lib = native_build.load_native(source, {})
        assert (lib is None) == (source.name in X86_SIMD), source.name
    commands = [line for line in log.read_text().splitlines() if ' -o ' in line]  # not --version
    assert len(commands) == len(SOURCES) - len(X86_SIMD)
    assert not any(flag in command for command in commands for flag in native_build.X86_FLAGS)
    for source in (s for s in SOURCES if s.name in X86_SIMD):
        assert 'x86-64 AVX2' in native_build._unsupported(source)
    assert native_build._unsupported() is not None  # without a source: the SIMD kernels
    built = {p.name.split('-')[0] for p in (tmp_path / 'cache' / 'depth_fusion_ros' / 'native').glob('*.so')}
    assert built == {s.stem for s in SOURCES if s.name not in X86_SIMD}


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a.numpy() if isinstance(a, torch.Tensor) else a).tobytes())
    return h.hexdigest()


def _filter_and_fusion_tests() -> tuple[str, str, str]:
    """The filter's end state on a synthetic room, the halo test's points and the guard's
    neighbour medians on a rendered keyframe, each as a digest."""
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
    from depth_fusion_ros.multiview.filter import DepthFilter

    seq = render_sequence(SynthConfig(width=160, height=120, frames=8, seed=4, parallax='high'))
    filt = DepthFilter(seq.camera, None, device='cpu')
    for frame in seq.frames:
        filt.process(frame.gray, frame.pose)
    state = _digest(*(getattr(filt.key.state, k) for k in ('mu', 'var', 'a', 'b')))
    image, single, m, points = rendered_halo_keyframe(width=160, height=120, point_share=0.6)
    halo = occlusion.halo_points(image, single, m, points)
    rows, cols = np.nonzero(points)
    values = np.log(m[rows, cols]).astype(np.float64)
    median = neighbour_median.nearest_median(cols, rows, values, radius=12.0, max_neighbours=8)
    return state, _digest(halo), _digest(*median)


def test_portable_gives_the_numbers_of_every_kernel_off(monkeypatch, tmp_path):
    """The filter with its choice of rows, bracket and update native but its search and
    descriptors torch's and OpenCV's (a combination only an ARM machine runs), the halo test
    and the guard's medians: what torch and numpy give with every kernel off, bit for bit."""
    _compiler_or_skip()
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path / 'cache'))
    results, ran = {}, {}
    for mode in ('0', 'portable'):
        monkeypatch.setenv('DEPTH_FUSION_NATIVE', mode)
        monkeypatch.setattr(native_build, '_loaded', {})
        modules = (native_cost, native_scores, *native_filter.KERNELS, native_halo, neighbour_median)
        ran[mode] = {m.__name__.rsplit('.', 1)[1] for m in modules if m.prepare()}
        results[mode] = _filter_and_fusion_tests()
    assert ran['0'] == set()
    plain = {'native_scores', 'native_choose', 'native_bracket', 'native_apply', 'native_halo'}
    assert ran['portable'] == plain | {'neighbour_median'}
    assert results['portable'] == results['0']
