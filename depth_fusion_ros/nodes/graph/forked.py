"""Node processes forked from a server that imported torch once (``depth-fusion run --processes``).

Why: importing torch costs each node process 1.3-1.5 s of CPU, more than the rest of its start
(the package, rclpy and its constructor: ~0.6 s). Three node processes on 2 cores each
imported it at once, so the slowest node was ready 3.4-3.6 s after it was started. A fork
server (``multiprocessing``'s ``forkserver``) imports torch and numpy once, then forks each
node from there: the children share those pages and start with their own imports.

Only torch and numpy are preloaded (then the server's own set-up, ``nodes/fork_server_setup``),
because only they are fork-safe here. Importing rclpy's extension starts two native threads
and OpenCV starts one. A fork keeps none of them, so a child could wait on a lock that a lost
thread held. Torch starts no thread at import, and numpy's OpenBLAS pool stops and restarts
around a fork with its own handlers.

Each child is still a process of its own, with its own rclpy context, DDS participant, GIL and
exit code. The launcher signals it, waits for it and reads its exit code through
:class:`ForkedNode`, which behaves like the ``subprocess.Popen`` it replaces. What the fork
server inherited at its start is replaced in the child: the environment (the node's own, as
a console script would get it), ``sys.argv`` (``--ros-args ...``), and stdout/stderr (the
node's log file). ``DEPTH_FUSION_FORK_NODES=0`` starts each node as its console script
instead (``spawn.node_command``).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import multiprocessing
import multiprocessing.forkserver
import os
import signal
import subprocess
import sys
import types
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: The switch: ``0`` starts console scripts (one interpreter each, torch imported in each).
FORK_ENV = 'DEPTH_FUSION_FORK_NODES'
#: What the fork server imports before it forks anything (see the module docstring), then its
#: own set-up: it outlives a stop signal sent to the process group, and freezes what it
#: imported out of the garbage collector's reach (fork_server_setup).
PRELOAD = ('numpy', 'torch', 'depth_fusion_ros.nodes.fork_server_setup')


def fork_nodes() -> bool:
    """Whether node processes are forked from the server (the default, where the platform can)."""
    value = os.environ.get(FORK_ENV, '1').strip().lower()
    if value not in ('0', '1', 'true', 'false', 'yes', 'no', 'on', 'off'):
        raise ValueError(f'{FORK_ENV}={value!r}: expected 1 (fork node processes) or 0 (console scripts)')
    wanted = value in ('1', 'true', 'yes', 'on')
    return wanted and 'forkserver' in multiprocessing.get_all_start_methods()


def forking_server(env: Mapping[str, str]) -> bool:
    """Whether this run forks its nodes: the switch allows it and the server runs with the
    nodes' thread variables (``env``; started now if needed). When not, the line that says why
    is logged and the nodes start as console scripts. A bad switch raises ``ValueError``."""
    if not fork_nodes():
        return False
    try:
        usable = start_server(env)
    except OSError as exc:  # no AF_UNIX socket, no process to spare: the scripts still work
        log.warning('node processes started as console scripts: the fork server did not start (%s)', exc)
        return False
    if not usable:
        log.info(
            'node processes started as console scripts: the fork server of this process runs with '
            'other thread variables (%s) and cannot be restarted',
            ', '.join(THREAD_VARIABLES),
        )
    return usable


def _context() -> Any:
    ctx = multiprocessing.get_context('forkserver')
    ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


#: The variables a library reads once, when it is loaded: the server must start with the nodes'
#: values (numpy's OpenBLAS sized its pool from them at the server's import and a forked
#: child keeps that pool: two spinning threads per node where one was asked cost the graph's
#: latency half again on 2 cores).
THREAD_VARIABLES = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')

#: The thread variables the running server was started with (``None``: no server yet).
_server_threads: dict[str, str] | None = None


def start_server(env: Mapping[str, str]) -> bool:
    """Start the fork server now, with the nodes' thread variables (``env``), so its imports
    overlap with the launcher's own set-up. A server of this process already running is kept
    when it was started with the same thread variables; when not, ``False``: it cannot be
    restarted (``multiprocessing`` has no public way), so start the nodes as console scripts."""
    global _server_threads
    wanted = _thread_variables(env)
    if _server_threads is not None:
        return _server_threads == wanted
    _context()
    with _server_environment(wanted):
        multiprocessing.forkserver.ensure_running()
    _server_threads = wanted
    return True


def _thread_variables(env: Mapping[str, str]) -> dict[str, str]:
    return {k: env[k] for k in THREAD_VARIABLES if k in env}


@contextlib.contextmanager
def _server_environment(threads: Mapping[str, str]) -> Iterator[None]:
    """This process's thread variables set to ``threads`` for as long as it may spawn the
    server: the server inherits the environment as it is at that moment. ``multiprocessing``
    also starts a new server inside ``Process.start()`` when the old one died (killed), so
    starts are wrapped too."""
    saved = {k: os.environ.get(k) for k in THREAD_VARIABLES}
    try:
        for k in THREAD_VARIABLES:
            os.environ.pop(k, None)
        os.environ.update(threads)
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def server_pid() -> int | None:
    """The pid of this process's fork server (``None``: not started), found among its children:
    its memory is part of the graph's (the bench counts it)."""
    me = str(os.getpid())
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            if stat.read_text().rsplit(')', 1)[1].split()[1] != me:
                continue
            if b'multiprocessing.forkserver' in (stat.parent / 'cmdline').read_bytes():
                return int(stat.parent.name)
        except (OSError, IndexError):  # gone meanwhile
            continue
    return None


class ForkedNode:
    """A forked node process seen as a ``subprocess.Popen``: ``pid``, ``returncode``,
    ``poll``, ``wait``, ``send_signal``, ``kill`` (what ``spawn.stop_processes`` and the run's
    lifecycle use). A negative return code is the signal that ended it, as with Popen."""

    def __init__(self, process: Any, args: Sequence[str]) -> None:
        self._process = process
        self.args = list(args)

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def returncode(self) -> int | None:
        return self._process.exitcode

    def poll(self) -> int | None:
        return self._process.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._process.join(timeout)
        code = self._process.exitcode
        if code is None:
            raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        return code

    def send_signal(self, signum: int) -> None:
        if self._process.exitcode is None:
            os.kill(self._process.pid, signum)

    def kill(self) -> None:
        if self._process.exitcode is None:
            self._process.kill()


def start_forked(
    module: str, argv: Sequence[str], env: Mapping[str, str], log_path: Path | None
) -> ForkedNode:
    """Fork ``module``'s ``main()`` from the server, with ``argv`` as its command line, ``env``
    as its environment and its output to ``log_path`` (appended; ``None``: this terminal).
    Raises ``RuntimeError`` when the server runs with other thread variables than ``env``'s."""
    if not start_server(env):
        raise RuntimeError(f'the fork server runs with other thread variables than {argv[0]} asks')
    process = _context().Process(
        target=_run_node,
        args=(module, list(argv), dict(env), str(log_path) if log_path else None),
        name=Path(argv[0]).name,
        daemon=True,  # terminated, not waited for, if this launcher exits without stopping it
    )
    with _main_left_alone(), _server_environment(_thread_variables(env)):
        process.start()
    return ForkedNode(process, argv)


@contextlib.contextmanager
def _main_left_alone() -> Iterator[None]:
    """Hide this process's main script from ``multiprocessing`` while a child starts.

    Like ``spawn``, the fork server runs the parent's main script again in each child (as
    ``__mp_main__``) unless it was run with ``python -m``. That script is the ``depth-fusion``
    CLI, or pytest, or a user's: each node would import what it imports and run whatever it
    runs outside a ``__main__`` guard (a test script's graph run started again in every child,
    before this). A node needs nothing from it, so it is swapped for an empty module for the
    few milliseconds in which ``start()`` reads it.
    """
    main = sys.modules['__main__']
    sys.modules['__main__'] = types.ModuleType('__main__')
    try:
        yield
    finally:
        sys.modules['__main__'] = main


def _run_node(module: str, argv: list[str], env: dict[str, str], log_path: str | None) -> None:
    """The child: become the console script ``argv[0]`` would have been, then run it."""
    for signum in (signal.SIGTERM, signal.SIGHUP):  # the server ignores them (fork_server_setup)
        signal.signal(signum, signal.SIG_DFL)
    os.environ.clear()
    os.environ.update(env)
    if log_path is not None:
        fd = os.open(log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        os.close(fd)
    # Line-buffered, as PYTHONUNBUFFERED makes a console script's: a log read while it runs
    # (or after a kill) holds every line written so far.
    sys.stdout = open(1, 'w', buffering=1, closefd=False)  # noqa: SIM115 - the process's own stdout
    sys.stderr = open(2, 'w', buffering=1, closefd=False)  # noqa: SIM115 - the process's own stderr
    sys.argv = list(argv)
    raise SystemExit(importlib.import_module(module).main())
