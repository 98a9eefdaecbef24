"""Fusion kernels built ahead of time (fusion/aot_kernels.py): found, used, same numbers, safe."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from depth_fusion_ros.fusion import aot_background, aot_kernels
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.fusion.weights import WeightParams

PARAMS = WeightParams()
CPU = torch.device('cpu')


@pytest.fixture(scope='module')
def built_cache(tmp_path_factory):
    """Both kernels built once into a private cache (~20-45 s on 2 cores), by the background
    builder a fusion node starts (fusion/aot_background.py): its own process, its log."""
    root = tmp_path_factory.mktemp('cache')
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv('XDG_CACHE_HOME', str(root))
        mp.delenv(aot_kernels.ENV_SWITCH, raising=False)
        aot_kernels._load.cache_clear()
        process = aot_background.spawn(PARAMS, aot_kernels.cache_dir())
        assert process.wait(600) == 0
        log = (aot_kernels.cache_dir() / aot_background.LOG_NAME).read_text()
    aot_kernels._load.cache_clear()
    seconds = {m.group(1): float(m.group(2)) for m in re.finditer(r'^(\w+): built in ([\d.]+) s', log, re.M)}
    return root, seconds


@pytest.fixture()
def cache(built_cache, monkeypatch):
    root, _ = built_cache
    monkeypatch.setenv('XDG_CACHE_HOME', str(root))
    monkeypatch.delenv(aot_kernels.ENV_SWITCH, raising=False)
    aot_kernels._load.cache_clear()
    yield root
    aot_kernels._load.cache_clear()


def _fuse(scene, compile_kernel: bool, mode: str = 'fast'):
    return interpolate(
        scene.single, scene.multi, np.isfinite(scene.multi), PARAMS, mode=mode, compile_kernel=compile_kernel
    )


def test_built_kernels_are_found_and_give_the_eager_numbers(cache, built_cache):
    assert set(built_cache[1]) == set(aot_kernels.KERNELS)
    assert aot_kernels.available(PARAMS, CPU)
    assert all(aot_kernels.kernel(name, PARAMS, CPU) is not None for name in aot_kernels.KERNELS)
    # through ctypes, which lets go of the GIL during the call (torch's runners hold it)
    assert all(hasattr(aot_kernels._load(n, PARAMS, 'cpu'), 'container') for n in aot_kernels.KERNELS)
    scene = make_scene(96, 72, n_points=300, seed=3)
    for mode in ('fast', 'exact'):
        ahead, eager = _fuse(scene, True, mode), _fuse(scene, False, mode)
        finite = np.isfinite(eager.offset)
        assert np.array_equal(finite, np.isfinite(ahead.offset))
        np.testing.assert_allclose(ahead.offset[finite], eager.offset[finite], atol=2e-5)
        np.testing.assert_allclose(ahead.support_distance[finite], eager.support_distance[finite], rtol=1e-4)


def test_one_point_and_other_parameters_take_the_other_paths(cache):
    """|Ω| = 1 is below the package's smallest size (two passes); other weight parameters
    have no package (the usual compile)."""
    scene = make_scene(40, 30, n_points=1, seed=1)
    np.testing.assert_allclose(
        _fuse(scene, True).offset, _fuse(scene, False).offset, atol=2e-5, equal_nan=True
    )
    other = WeightParams(sigma1=9.0)
    assert not aot_kernels.available(other, CPU) and aot_kernels.kernel('sums', other, CPU) is None


def test_a_fusion_node_with_built_kernels_only_loads_them(cache):
    """fusion_warmup: the background warm-up finds the packages, says so and gets warm."""
    from depth_fusion_ros.fusion.pipeline import FusionConfig
    from depth_fusion_ros.nodes.fusion_warmup import start_kernels

    lines: list[str] = []

    class Logger:
        def info(self, text: str) -> None:
            lines.append(text)

        warning = info

    class Node:
        def get_logger(self) -> Logger:
            return Logger()

    node = Node()
    config = FusionConfig(mode='fast', compile_kernel=True, max_points=512)
    first = start_kernels(node, config, background=True)
    assert first.compile_kernel is False  # eager until the thread is done
    node.compile_thread.join(120)
    assert node.kernels_ready.is_set() and node.active_config == config
    assert any('built ahead of time found' in line for line in lines), lines
    assert any('loaded (built ahead of time)' in line for line in lines), lines


def test_the_cli_builds_only_when_missing(cache, capsys):
    from depth_fusion_ros.cli.main import main

    assert main(['kernels', '--if-missing']) == 0
    assert 'already in' in capsys.readouterr().out


def test_switched_off_or_broken_packages_are_not_used(cache, monkeypatch, caplog):
    monkeypatch.setenv(aot_kernels.ENV_SWITCH, '0')
    assert aot_kernels.kernel('sums', PARAMS, CPU) is None and not aot_kernels.available(PARAMS, CPU)
    monkeypatch.delenv(aot_kernels.ENV_SWITCH)
    other = WeightParams(sigma2=0.2)
    broken = aot_kernels.package_path('sums', other, CPU)
    broken.write_bytes(b'not a package')
    try:
        assert aot_kernels.kernel('sums', other, CPU) is None
        assert 'ignoring the AOT fusion kernel' in caplog.text
    finally:
        broken.unlink()
    with pytest.raises(ValueError, match='CPU only'):
        aot_kernels.build(PARAMS, 'cuda')


def test_a_second_builder_gives_way_and_a_waiting_one_finds_the_kernels(cache):
    """The cache's build lock: a builder that may not wait gives up (None) while another holds
    the lock; one that waits then finds nothing missing ({})."""
    with aot_kernels.build_lock(wait=True) as held:
        assert held
        assert aot_kernels.build_if_missing(PARAMS, wait=False) is None
    assert aot_kernels.build_if_missing(PARAMS, wait=True) == {}


def test_a_node_that_compiles_starts_the_builder_for_its_own_parameters(cache, monkeypatch):
    """fusion_warmup.build_for_the_next_start: nothing when the kernels are built (or the cache
    is off); otherwise the builder for the node's weight parameters, said in one line."""
    from depth_fusion_ros.fusion.pipeline import FusionConfig
    from depth_fusion_ros.nodes import fusion_warmup

    lines: list[str] = []
    started: list[WeightParams] = []

    class Logger:
        def info(self, text: str) -> None:
            lines.append(text)

        warning = info

    class Node:
        def get_logger(self) -> Logger:
            return Logger()

    class Process:
        pid = 4242

    monkeypatch.setattr(aot_background, 'spawn', lambda params, root: started.append(params) or Process())
    assert not fusion_warmup.build_for_the_next_start(Node(), FusionConfig(compile_kernel=True))
    other = FusionConfig(compile_kernel=True, sigma1=9.0)
    monkeypatch.setenv(aot_kernels.ENV_SWITCH, '0')
    assert not fusion_warmup.build_for_the_next_start(Node(), other)
    monkeypatch.delenv(aot_kernels.ENV_SWITCH)
    node = Node()
    assert fusion_warmup.build_for_the_next_start(node, other)
    assert started == [other.weight_params] and node.kernel_builder.pid == 4242
    assert 'process 4242 at the lowest CPU priority' in lines[-1]
