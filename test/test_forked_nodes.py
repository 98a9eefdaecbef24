"""Node processes forked from the fork server (nodes/graph/forked.py) behave like the console
scripts they replace: their own environment, command line, log file, threads, exit codes and
signals, seen through a Popen-like handle."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from depth_fusion_ros.nodes.graph import forked
from depth_fusion_ros.nodes.graph.dds import orphan_segments, participant_segments_of, remove_segments
from depth_fusion_ros.nodes.graph.forked import FORK_ENV, fork_nodes, server_pid, start_forked
from depth_fusion_ros.nodes.threads import node_threads

pytestmark = pytest.mark.skipif(
    'forkserver' not in __import__('multiprocessing').get_all_start_methods(), reason='no fork server here'
)


def node_threads_here() -> str:
    """The thread share ``depth-fusion run --processes`` gives a node on this machine: the fork
    server keeps the thread variables it started with, so every test here asks for the same."""
    return os.environ.get('OMP_NUM_THREADS') or str(node_threads())


def node_env(**extra: str) -> dict[str, str]:
    """This test's environment (its isolated ROS domain), with the node's thread share."""
    return {**os.environ, 'RCUTILS_COLORIZED_OUTPUT': '0', 'OMP_NUM_THREADS': node_threads_here(), **extra}


def main() -> int:
    """What ``test_a_forked_child_has_the_blas_threads_its_environment_asks`` forks: prints the
    OpenBLAS threads of numpy, which OpenBLAS sized when the fork server imported numpy."""
    import ctypes

    import numpy

    names = ('scipy_openblas_get_num_threads64_', 'openblas_get_num_threads64_', 'openblas_get_num_threads')
    for lib_path in (Path(numpy.__file__).parent.parent / 'numpy.libs').glob('*openblas*'):
        lib = ctypes.CDLL(str(lib_path))
        for name in names:
            if hasattr(lib, name):
                print(f'openblas threads: {getattr(lib, name)()}', flush=True)
                return 0
    print('no OpenBLAS found', flush=True)
    return 3


def wait_ready(node: forked.ForkedNode, log: Path) -> None:
    """Until the node logged its ready line (it handles SIGINT and SIGTERM from then on)."""
    for _ in range(600):
        if log.exists() and 'ready' in log.read_text():
            return
        assert node.poll() is None, log.read_text()
        time.sleep(0.1)
    raise AssertionError(f'not ready after 60 s: {log.read_text() if log.exists() else "no log"}')


def test_a_forked_node_gets_its_own_command_line_environment_threads_and_exit_code(tmp_path: Path):
    """A bad parameter given on the forked node's ``--ros-args`` ends it with exit code 2 and
    one line naming the parameter in its own log, after the node applied the ``OMP_NUM_THREADS``
    of its environment to torch (which the fork server imported)."""
    log = tmp_path / 'fusion_node.log'
    argv = ['fusion_node', '--ros-args', '-p', 'input_qos:=bogus']
    node = start_forked('depth_fusion_ros.nodes.fusion_node', argv, node_env(), log)
    assert node.wait(120) == 2
    assert node.poll() == 2 and node.returncode == 2
    text = log.read_text()
    assert f'torch and OpenCV threads: {node_threads_here()} (OMP_NUM_THREADS)' in text, text
    errors = [line for line in text.splitlines() if line.startswith('[ERROR]')]
    assert len(errors) == 1 and 'input_qos' in errors[0], text
    assert 'Traceback' not in text


def remove_own_orphans(mapped: set[str], since: float) -> None:
    """Remove the Fast DDS segments a node killed here left: the orphans since the test began
    (dds.orphan_segments: owner gone) among those it mapped, with their lock files. ``run`` and
    ``launch`` do this for the nodes they start; a test that kills one itself must, or the
    segments stay in /dev/shm, where the graph tests on the other worker count them as left
    behind."""
    remove_segments([n for n in orphan_segments(since) if n.removesuffix('_el') in mapped])


@pytest.mark.parametrize(('signum', 'code'), [(signal.SIGINT, 0), (signal.SIGKILL, -9)])
def test_a_forked_node_stops_on_sigint_and_reports_a_kill(tmp_path: Path, signum: int, code: int):
    """A running forked node: ``wait`` with a timeout raises as Popen's does; SIGINT stops it
    cleanly (exit 0, final counters logged); SIGKILL reads as -9, as ``describe_exit`` expects."""
    since = time.time()
    log = tmp_path / 'multi_view_node.log'
    node = start_forked(
        'depth_fusion_ros.nodes.multi_view_node', ['multi_view_node', '--ros-args'], node_env(), log
    )
    mapped: set[str] = set()
    try:
        wait_ready(node, log)
        mapped = participant_segments_of(node.pid)
        with pytest.raises(subprocess.TimeoutExpired):
            node.wait(0.2)
        if signum == signal.SIGKILL:
            node.kill()
        else:
            node.send_signal(signum)
        assert node.wait(60) == code, log.read_text()
    finally:
        node.kill()
        node.wait(60)
        remove_own_orphans(mapped, since)
    if code == 0:
        assert 'final counters' in log.read_text()
    node.send_signal(signal.SIGINT)  # stopped already: nothing is sent to a pid that may be reused


def test_the_switch_takes_console_scripts_and_rejects_a_bad_value(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv(FORK_ENV, '0')
    assert fork_nodes() is False
    monkeypatch.setenv(FORK_ENV, '1')
    assert fork_nodes() is True
    monkeypatch.setenv(FORK_ENV, 'maybe')
    with pytest.raises(ValueError, match=FORK_ENV):
        fork_nodes()


def test_a_stop_signal_to_the_fork_server_loses_no_exit_code(tmp_path: Path):
    """SIGTERM sent to the process group reaches the server too; it ignores it, so the node's
    own exit code still comes back (not the 255 of a server that died first)."""
    log = tmp_path / 'fusion_node.log'
    node = start_forked('depth_fusion_ros.nodes.fusion_node', ['fusion_node', '--ros-args'], node_env(), log)
    try:
        wait_ready(node, log)
        server = server_pid()
        assert server is not None
        os.kill(server, signal.SIGTERM)
        os.kill(server, signal.SIGHUP)
        node.send_signal(signal.SIGTERM)  # the node's own handler: a clean stop
        assert node.wait(60) == 0, log.read_text() if log.exists() else ''
        assert server_pid() == server
    finally:
        node.kill()


def test_a_forked_child_has_the_blas_threads_its_environment_asks(tmp_path: Path):
    """numpy's OpenBLAS sizes its pool when it is loaded, in the fork server: the server starts
    with the nodes' thread variables, so a child gets one thread, not one per core (two
    spinning OpenBLAS threads per node slowed the graph on 2 cores)."""
    log = tmp_path / 'probe.log'
    node = start_forked(__name__, ['probe'], node_env(), log)
    code = node.wait(60)
    if code == 3:
        pytest.skip('this numpy has no OpenBLAS of its own')
    assert code == 0, log.read_text()
    assert f'openblas threads: {node_threads_here()}' in log.read_text()
    with pytest.raises(RuntimeError, match='other thread variables'):
        start_forked(__name__, ['probe'], node_env(OMP_NUM_THREADS=str(int(node_threads_here()) + 1)), log)


def test_a_fork_server_that_was_killed_is_replaced_with_the_nodes_threads(tmp_path: Path):
    """``multiprocessing`` starts a new server inside ``start()`` when its server died; that one
    too gets the nodes' thread variables, not this process's."""
    log = tmp_path / 'probe.log'
    assert start_forked(__name__, ['probe'], node_env(), log).wait(60) in (0, 3)
    server = server_pid()
    assert server is not None
    os.kill(server, signal.SIGKILL)
    stat = Path(f'/proc/{server}/stat')
    for _ in range(100):  # dead (a zombie until multiprocessing reaps it), not only dying
        if not stat.exists() or stat.read_text().rsplit(')', 1)[1].split()[0] == 'Z':
            break
        time.sleep(0.05)
    log.unlink()
    code = start_forked(__name__, ['probe'], node_env(), log).wait(60)
    if code == 3:
        pytest.skip('this numpy has no OpenBLAS of its own')
    assert server_pid() not in (None, server)
    assert f'openblas threads: {node_threads_here()}' in log.read_text()
