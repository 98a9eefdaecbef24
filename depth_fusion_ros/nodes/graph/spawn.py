"""Starting and stopping node processes (``depth-fusion run --processes``).

Each node runs as its console script with ``--ros-args``; when a child does not stop on SIGINT
it is killed and the shared-memory segments it left are removed.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TextIO

from ..threads import node_threads
from .dds import orphan_segments, remove_segments
from .forked import start_forked
from .param_merge import ros_arg_value

log = logging.getLogger(__name__)


def node_class(module: Any) -> type:
    """The Node subclass a node module defines (``SingleViewNode``, ...)."""
    from rclpy.node import Node

    for value in vars(module).values():
        if isinstance(value, type) and issubclass(value, Node) and value.__module__ == module.__name__:
            return value
    raise ImportError(f'{module.__name__} defines no rclpy Node subclass')


def node_command(script: str, module: str, ros_args: list[str]) -> list[str]:
    """Command line of a node: its console script when installed, else ``python -m module``."""
    candidates = [Path(sys.executable).parent / script]
    found = shutil.which(script)
    if found:
        candidates.append(Path(found))
    for exe in candidates:
        if exe.is_file() and os.access(exe, os.X_OK):
            return [str(exe), '--ros-args', *ros_args]
    return [sys.executable, '-m', module, '--ros-args', *ros_args]


def describe_exit(code: int) -> str:
    """``'was killed by SIGKILL (exit -9)'`` or ``'exited early with code 1'``: a node that
    stopped while the run still needed it."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f'signal {-code}'
        return f'was killed by {name} (exit {code})'
    return f'exited early with code {code}'


def node_environment(threads_per_node: int | None) -> dict[str, str]:
    """The environment of every node process: this process's, with the node's torch thread
    share (``threads_per_node``, else what a node script takes: ``threads.node_threads``)."""
    env = os.environ.copy()
    env.setdefault('PYTHONUNBUFFERED', '1')
    threads = threads_per_node if threads_per_node is not None else node_threads(env)
    if threads is not None:  # None: OMP_NUM_THREADS is set, and it is in env already
        env['OMP_NUM_THREADS'] = str(threads)
    return env


def node_ros_args(params_file: Path | None, values: Mapping[str, Any]) -> list[str]:
    """A node's arguments after ``--ros-args``: the params file, then ``-p`` for each value."""
    args = ['--params-file', str(params_file)] if params_file else []
    for key, value in values.items():
        args += ['-p', f'{key}:={ros_arg_value(value)}']
    return args


def run_header(script: str) -> str:
    """The line that opens one run's part of a node log: ``=== fusion_node started 2026-12-02
    02:50:01 UTC by depth-fusion (pid 1234) ===``."""
    when = time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())
    return f'=== {script} started {when} by depth-fusion (pid {os.getpid()}) ===\n'


def start_node(
    script: str, module: str, ros_args: list[str], env: dict[str, str], log_path: Path | None, fork: bool
) -> tuple[Any, TextIO | None]:
    """Start one node: forked from the fork server (``forked.start_forked``), or as its console
    script. Its output goes to ``log_path`` (appended after a line that opens this run,
    uncoloured) or to this terminal. Returns the Popen-like process and the log file this
    process holds open for a console script (``None`` otherwise), which the caller closes once
    the node has stopped.

    Appended, not emptied: a graph started again with the same ``--log-dir`` (after a crash,
    say) kept only the new run's logs, and the crash's were lost."""
    out = None
    if log_path is not None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        out = open(log_path, 'a')  # noqa: SIM115 - returned, closed by the caller
        out.write(run_header(script))
        out.flush()
    if fork:
        if out is not None:
            out.close()  # the child appends to it itself
            env = {**env, 'RCUTILS_COLORIZED_OUTPUT': '0'}
        return start_forked(module, [script, '--ros-args', *ros_args], env, log_path), None
    return popen_node(node_command(script, module, ros_args), env, out), out


def popen_node(cmd: list[str], env: dict[str, str], log_file: TextIO | None) -> subprocess.Popen:
    """Start one node process, logging to ``log_file`` (uncoloured) or to this terminal."""
    if log_file is None:
        return subprocess.Popen(cmd, env=env)
    return subprocess.Popen(
        cmd, env={**env, 'RCUTILS_COLORIZED_OUTPUT': '0'}, stdout=log_file, stderr=log_file
    )


# Seconds a node process has to stop on SIGINT before it is killed, and after which a node still
# stopping writes its threads' stacks to its log (console.run_node) so a kill says where it hung. A
# normal stop takes < 2 s (a worker finishing its keyframe, a map saved on shutdown: ~10 s).
STOP_TIMEOUT_S = 15.0
STOP_STACKS_AFTER_S = 12.0


def stop_processes(
    processes: dict[str, Any], interrupted: bool, timeout: float = STOP_TIMEOUT_S
) -> dict[str, int | None]:
    """SIGINT each child still running (after a grace period on Ctrl-C, which they got too).

    ``processes``: ``subprocess.Popen`` objects or what behaves like them (``forked.ForkedNode``).

    A child that does not stop within ``timeout`` is killed (its shared memory is for
    :func:`remove_segments_of_killed`). Returns the exit codes by node name.
    """
    if interrupted:
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline and any(p.poll() is None for p in processes.values()):
            time.sleep(0.05)
    for p in processes.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + timeout
    for name, p in processes.items():
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            stacks = "; its log has its threads' stacks" if timeout > STOP_STACKS_AFTER_S else ''
            log.warning('%s did not stop on SIGINT within %.0f s: killing it%s', name, timeout, stacks)
            p.kill()
            p.wait()
    return {name: p.returncode for name, p in processes.items()}


def remove_segments_of_killed(codes: dict[str, int | None], since: float) -> None:
    """After a node was killed by a signal (by :func:`stop_processes` or by someone else: kill
    -9, the OOM killer), remove the shared-memory segments created after ``since`` (epoch s)
    whose owner is gone (:func:`~.dds.orphan_segments`): a killed node had no shutdown to
    remove its own. Called once this process's own participants are gone too (a listener, a
    recorder): the port segments are judged by who maps them, and each participant maps
    them."""
    if not any(code is not None and code < 0 for code in codes.values()):
        return
    orphans = orphan_segments(since, include_ports=True)
    if orphans:
        log.warning('removing %d shared-memory segments left by killed nodes', len(orphans))
        remove_segments(orphans)
