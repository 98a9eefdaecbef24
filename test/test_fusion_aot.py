"""Fusion kernels built ahead of time (fusion/aot_kernels.py): found, used, same numbers, safe."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from depth_fusion_ros import native_build
from depth_fusion_ros.fusion import aot_background, aot_kernels
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.fusion.weights import WeightParams

PARAMS = WeightParams()
_REPO = Path(__file__).resolve().parents[1]
CPU = torch.device('cpu')


class _Logger:
    def __init__(self, lines: list[str]) -> None:
        self.lines = lines

    def info(self, text: str) -> None:
        self.lines.append(text)

    warning = info


class _Node:
    """What fusion_warmup needs of a node: a logger whose lines the test reads."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def get_logger(self) -> _Logger:
        return _Logger(self.lines)


@pytest.fixture(scope='module')
def built_cache(tmp_path_factory):
    """Both kernels built once into a private, empty cache (~30-45 s on 2 cores) the way a
    fusion node on a cold machine gets them (fusion_warmup, build_ahead): the background
    builder of fusion/aot_background.py in a process of its own, waited for, then loaded."""
    from depth_fusion_ros.fusion.pipeline import FusionConfig
    from depth_fusion_ros.nodes.fusion_warmup import start_kernels

    root = tmp_path_factory.mktemp('cache')
    node = _Node()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv('XDG_CACHE_HOME', str(root))
        mp.delenv(aot_kernels.ENV_SWITCH, raising=False)
        # what a node on 2 cores has set (nodes/threads.py), and so its builder inherits
        mp.setenv('OMP_NUM_THREADS', '1')
        aot_kernels.forget_loaded()
        config = FusionConfig(mode='fast', compile_kernel=True, max_points=512)
        assert start_kernels(node, config, background=True, build_ahead=True).compile_kernel is False
        node.compile_thread.join(600)
        assert node.kernels_ready.is_set() and node.active_config == config
        assert node.kernel_builder.returncode == 0
        log = (aot_kernels.cache_dir() / aot_background.LOG_NAME).read_text()
    aot_kernels.forget_loaded()
    assert any('building the fusion kernels ahead of time: process' in line for line in node.lines), (
        node.lines
    )
    assert any('loaded (built ahead of time)' in line for line in node.lines), node.lines
    seconds = {m.group(1): float(m.group(2)) for m in re.finditer(r'^(\w+): built in ([\d.]+) s', log, re.M)}
    return root, seconds


@pytest.fixture()
def cache(built_cache, monkeypatch):
    root, _ = built_cache
    monkeypatch.setenv('XDG_CACHE_HOME', str(root))
    monkeypatch.delenv(aot_kernels.ENV_SWITCH, raising=False)
    aot_kernels.forget_loaded()
    yield root
    aot_kernels.forget_loaded()


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


def test_kernels_built_in_a_one_thread_process_run_on_the_callers_threads(cache):
    """The builder ran with ``OMP_NUM_THREADS=1`` (the fixture): its libraries must still hold
    a parallel loop (an OpenMP region sized at run time), or every process that loads them
    fuses on one core whatever its ``torch.set_num_threads``. The numbers do not depend on it."""
    for name in aot_kernels.KERNELS:
        library = aot_kernels.package_path(name, PARAMS, CPU).read_bytes()
        # GCC's OpenMP (libgomp, torch's own on Linux) or LLVM's (a clang build): either entry point
        assert b'GOMP_parallel' in library or b'__kmpc_fork_call' in library, f'{name}: no parallel loop'
    scene = make_scene(96, 72, n_points=300, seed=4)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _fuse(scene, True, 'exact')
        torch.set_num_threads(2)
        two = _fuse(scene, True, 'exact')
    finally:
        torch.set_num_threads(threads)
    np.testing.assert_allclose(two.offset, one.offset, atol=1e-6, equal_nan=True)


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

    node = _Node()
    config = FusionConfig(mode='fast', compile_kernel=True, max_points=512)
    first = start_kernels(node, config, background=True, build_ahead=True)
    assert first.compile_kernel is False  # eager until the thread is done
    node.compile_thread.join(120)
    assert node.kernels_ready.is_set() and node.active_config == config
    assert any('built ahead of time found' in line for line in node.lines), node.lines
    assert any('loaded (built ahead of time)' in line for line in node.lines), node.lines
    assert not hasattr(node, 'kernel_builder')  # nothing to build


def test_the_cli_builds_only_when_missing(cache, capsys):
    from depth_fusion_ros.cli.main import main

    assert main(['kernels', '--if-missing']) == 0
    out = capsys.readouterr().out
    assert 'already in' in out
    if native_build.unavailable() is None:  # the C kernels too, and for which CPU
        assert f'native C kernels: 8 of 8 ready for {native_build.build_target()}' in out
    else:
        assert 'native C kernels: not used here' in out
    assert main(['kernels', '--if-missing', '--background']) == 0
    assert 'already in' in capsys.readouterr().out


def test_the_cli_can_start_the_background_builder(cache, capsys, monkeypatch):
    """``depth-fusion kernels --background`` (scripts/test.sh): the builder a node starts, then
    back at once."""
    from depth_fusion_ros.cli.main import main
    from depth_fusion_ros.fusion.pipeline import FusionConfig

    started: list[WeightParams] = []

    class Process:
        pid = 4243

    monkeypatch.setattr(aot_background, 'spawn', lambda params, root: started.append(params) or Process())
    assert main(['kernels', '--background']) == 0
    assert started == [FusionConfig().weight_params]  # the node's defaults
    assert 'process 4243 at the lowest CPU priority' in capsys.readouterr().out


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


def test_the_builder_starts_only_where_kernels_are_missing_and_a_failed_build_means_compiling(
    cache, monkeypatch
):
    """fusion_warmup.start_builder: nothing when the kernels are built or the cache is off;
    otherwise the builder for the node's own weight parameters, said in one line. A build that
    ends without kernels is said too, and the node compiles in its process instead."""
    from depth_fusion_ros.fusion.pipeline import FusionConfig
    from depth_fusion_ros.nodes import fusion_warmup

    started: list[WeightParams] = []

    class Failed:
        pid = 4242

        def wait(self) -> int:
            return 1

    monkeypatch.setattr(aot_background, 'spawn', lambda params, root: started.append(params) or Failed())
    assert not fusion_warmup.start_builder(_Node(), FusionConfig(compile_kernel=True), 'eager')
    other = FusionConfig(compile_kernel=True, sigma1=9.0)
    monkeypatch.setenv(aot_kernels.ENV_SWITCH, '0')
    assert not fusion_warmup.start_builder(_Node(), other, 'eager')
    monkeypatch.delenv(aot_kernels.ENV_SWITCH)
    node = _Node()
    assert fusion_warmup.start_builder(node, other, 'eager meanwhile')
    assert started == [other.weight_params] and node.kernel_builder.pid == 4242
    assert 'process 4242 at the lowest CPU priority' in node.lines[-1] and 'eager meanwhile' in node.lines[-1]
    assert not fusion_warmup._wait_for_builder(node, other)
    assert 'ended without them (exit 1' in node.lines[-1] and 'compiling in this process' in node.lines[-1]


def test_shutdown_does_not_wait_for_a_builder_process():
    """fusion_warmup.finish_compiling: a warm-up thread that only waits for the builder (a
    process of its own, which goes on) holds no shutdown; one that compiles here is waited for."""
    import threading

    from depth_fusion_ros.nodes import fusion_warmup

    release = threading.Event()
    node = _Node()
    node.compile_thread = threading.Thread(target=release.wait, daemon=True)
    node.compile_thread.start()
    try:
        node.waiting_for_builder = True
        assert fusion_warmup.finish_compiling(node, 30.0)
        node.waiting_for_builder = False
        assert not fusion_warmup.finish_compiling(node, 0.0)
    finally:
        release.set()
    node.compile_thread.join(5)
    assert fusion_warmup.finish_compiling(node, 0.0)


_PROGRESS_BAR_CHILD = """
import multiprocessing, os, sys

def child(give_thread_lock):
    if give_thread_lock:
        from depth_fusion_ros.nodes.fusion_warmup import thread_lock_for_progress_bars
        thread_lock_for_progress_bars()
    from tqdm import tqdm
    for _ in tqdm(range(2), disable=True):  # what torch.fx's interpreter does while it compiles
        pass
    os._exit(0)  # fusion_warmup.exit_now_if_compiling: a node stopped while it compiles

if __name__ == '__main__':
    process = multiprocessing.get_context('forkserver').Process(target=child, args=(sys.argv[1] == '1',))
    process.start()
    process.join()
    sys.exit(process.exitcode)
"""


@pytest.mark.parametrize('give_thread_lock', [False, True])
def test_a_node_stopped_while_it_compiles_leaves_no_semaphore_behind(tmp_path, give_thread_lock):
    """fusion_warmup.thread_lock_for_progress_bars: a forked node whose compilation drew a tqdm
    bar and that then ended with ``os._exit`` left tqdm's multiprocessing lock to the
    launcher's resource tracker, which warned of a leaked semaphore at every such stop. The
    unfixed case is run too, so the test shows it still detects the leak."""
    import multiprocessing
    import os
    import subprocess
    import sys

    if 'forkserver' not in multiprocessing.get_all_start_methods():
        pytest.skip('no forkserver start method on this platform')
    script = tmp_path / 'child.py'
    script.write_text(_PROGRESS_BAR_CHILD)
    env = {
        **os.environ,
        'PYTHONPATH': os.pathsep.join(filter(None, [str(_REPO), os.environ.get('PYTHONPATH')])),
    }
    done = subprocess.run(
        [sys.executable, str(script), '1' if give_thread_lock else '0'],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert done.returncode == 0, done.stderr
    assert ('leaked semaphore' in done.stderr) is not give_thread_lock, done.stderr


def test_the_bench_says_which_kernels_its_compiled_rows_ran(cache, tmp_path, monkeypatch):
    """``bench --only fusion``'s compiled rows differ several times between the library built
    ahead of time, an in-process compile and eager code: each row's note names the one it ran."""
    from depth_fusion_ros.fusion import kernel_compile
    from depth_fusion_ros.fusion.kernel_compile import kernel_source

    assert kernel_source(PARAMS, 'cpu').startswith('kernels built ahead of time')
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path))
    assert kernel_source(PARAMS, 'cpu') == 'kernels compiled by torch.compile in this process'
    monkeypatch.setattr(kernel_compile, 'COMPILE_FAILED', {'cpu'})
    assert kernel_source(PARAMS, 'cpu').startswith('eager')


def test_libraries_unused_for_long_are_pruned_and_a_load_marks_one_used(cache, tmp_path):
    """Each torch upgrade or kernel change leaves the old libraries behind: a build deletes
    those nobody loaded for ``UNUSED_DAYS``, never the ones it keeps, and other files not."""
    import os
    import time

    old = time.time() - (aot_kernels.UNUSED_DAYS + 1) * 86400.0
    names = ('fusion_sums_stale.so', 'fusion_blend_recent.so', 'fusion_sums_kept.so', 'build.lock')
    for name in names:
        (tmp_path / name).write_bytes(b'x')
        if name != 'fusion_blend_recent.so':
            os.utime(tmp_path / name, (old, old))
    removed = aot_kernels.prune_unused(tmp_path, 'fusion_*.so', keep=[tmp_path / 'fusion_sums_kept.so'])
    assert [p.name for p in removed] == ['fusion_sums_stale.so']
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names[1:])

    built = aot_kernels.package_path('sums', PARAMS, CPU)
    os.utime(built, (old, old))
    aot_kernels.forget_loaded()
    assert aot_kernels.kernel('sums', PARAMS, CPU) is not None
    assert built.stat().st_mtime > time.time() - 600  # loaded: marked used, so never pruned
