"""Getting the fusion kernels ready without making the node late to subscribe.

``torch.compile`` of the fusion kernels takes 10+ s on 2 CPU cores. Done in the constructor,
the node subscribes (and says it is ready) only after that, so a whole graph waits for it. In
the background instead, the node is ready at once and fuses with the eager kernels (same
arithmetic, slower) until the compiled ones are built; then it switches. A paced replay loses
nothing either way; a live camera gets its first keyframes fused a little slower.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import threading
import time
from typing import Any

from ..fusion.pipeline import FusionConfig, warm_up

COMPILE_THREAD = 'fusion-compile'


def start_kernels(
    node: Any, config: FusionConfig, background: bool, build_ahead: bool = False
) -> FusionConfig:
    """The config ``node`` fuses with from now on; compiles now, or on a thread that then sets
    ``node.active_config = config`` (``node.kernels_ready`` is set when compiled kernels run).

    ``build_ahead``: where no kernels were built ahead of time (CPU), the background thread
    starts the low-priority builder of ``fusion/aot_background.py`` and waits for it instead of
    compiling in this process, then loads what it built. Measured on a cold machine, 7-Scenes
    at 30 Hz with the three console nodes (docs/performance.md, "A cold machine"): 44-46 of 49
    keyframes fused against 31-32 while compiling in the node (``torch.compile`` takes a core
    and, tracing in Python, the GIL from the node's own worker for 15-25 s); and every later
    start is warm. Without it (or when the build fails) the node compiles as before. In the
    constructor (``background`` false) the node compiles and starts the builder for the next
    start."""
    node.kernels_ready = threading.Event()
    if not config.compile_kernel:
        node.kernels_ready.set()
        return config
    if not background:
        ahead = _ahead_of_time(node, config)
        if build_ahead and not ahead and start_builder(node, config, 'compiling here too'):
            # reaped when it ends (nothing here waits for it): no zombie left beside the node
            reaper = threading.Thread(target=node.kernel_builder.wait, name='fusion-reaper', daemon=True)
            reaper.start()
        seconds = warm_up(config)
        node.get_logger().info(f'fusion kernels ready (compiled in {seconds:.1f} s)')
        node.kernels_ready.set()
        return config

    def compile_then_switch() -> None:
        start = time.monotonic()
        thread_lock_for_progress_bars()
        ahead = _ahead_of_time(node, config)  # here, not in the constructor: it imports inductor (~1 s)
        meanwhile = 'fusing with the eager kernels until then'
        if build_ahead and not ahead and start_builder(node, config, meanwhile):
            node.waiting_for_builder = True  # only a waitpid: nothing to finish at shutdown
            ahead = _wait_for_builder(node, config)
            node.waiting_for_builder = False
            if getattr(node, '_destroyed', False):
                return
        try:
            warm_up(config)  # with kernels built ahead of time this only loads them
        except Exception as exc:  # eager stays in use: slower, never wrong
            node.get_logger().warning(f'compiling the fusion kernels failed ({exc!r}); staying eager')
            _say_warm(node, 'fusion kernels stay eager: warm')  # no faster state is coming
            return
        if getattr(node, '_destroyed', False):
            return
        node.active_config = config
        node.kernels_ready.set()
        how = 'loaded (built ahead of time)' if ahead else 'compiled in the background'
        node.get_logger().info(f'fusion kernels {how} in {time.monotonic() - start:.1f} s; switched')
        _say_warm(node, f'fusion kernels {"ahead of time" if ahead else "compiled"}: warm')

    node.compile_thread = threading.Thread(target=compile_then_switch, name=COMPILE_THREAD, daemon=True)
    node.compile_thread.start()
    return dataclasses.replace(config, compile_kernel=False)


def thread_lock_for_progress_bars() -> None:
    """Give tqdm a thread lock before torch compiles here. ``torch.fx``'s interpreter opens a
    tqdm bar while it compiles, and tqdm's first bar makes a ``multiprocessing`` RLock: in a
    node forked by the launcher's fork server, a named semaphore that ``multiprocessing``
    unlinks only at a normal exit. A node stopped while it compiles ends with ``os._exit``
    (:func:`exit_now_if_compiling`), so the semaphore outlived it and the launcher's resource
    tracker printed "There appear to be 1 leaked semaphore objects" at such stops (4 of 7 in
    one measurement). The bars of this process are drawn by its own threads only, which a
    thread lock serialises as well."""
    try:
        from tqdm import tqdm
    except ImportError:  # torch draws no bar then
        return
    tqdm.set_lock(threading.RLock())


def _wait_for_builder(node: Any, config: FusionConfig) -> bool:
    """Wait for the builder ``start_builder`` started; True when its kernels are there."""
    from ..fusion import aot_background, aot_kernels

    code = node.kernel_builder.wait()
    if aot_kernels.available(config.weight_params, config.device):
        return True
    log = aot_kernels.cache_dir() / aot_background.LOG_NAME
    node.get_logger().warning(
        f'the background build of the fusion kernels ended without them (exit {code}; log {log}): '
        'compiling in this process'
    )
    return False


def _ahead_of_time(node: Any, config: FusionConfig) -> bool:
    """Whether ``depth-fusion kernels`` built this config's kernels (fusion/aot_kernels.py):
    then the warm-up below only loads them (~2 s, mostly importing the loader) instead of
    compiling (5-9 s on 2 cores). Says which, and how to get the fast start."""
    import torch

    from ..fusion import aot_kernels

    device = torch.device(config.device)
    if not aot_kernels.enabled(device):
        return False
    if aot_kernels.available(config.weight_params, device):
        node.get_logger().info(f'fusion kernels built ahead of time found in {aot_kernels.cache_dir()}')
        return True
    node.get_logger().info(
        'no fusion kernels built ahead of time for these weight parameters (depth-fusion kernels builds them '
        'once; then every fusion node is warm within seconds of starting)'
    )
    return False


def start_builder(node: Any, config: FusionConfig, meanwhile: str) -> bool:
    """Start the background builder of the node's kernels (CPU only, where the cache is in use
    and they are still missing) as ``node.kernel_builder``; logs one line, which says what the
    node does ``meanwhile``. True when started."""
    import torch

    from ..fusion import aot_background, aot_kernels

    device = torch.device(config.device)
    params = config.weight_params
    if not aot_kernels.enabled(device) or aot_kernels.available(params, device):
        return False
    try:
        process = aot_background.spawn(params, aot_kernels.cache_dir())
    except OSError as exc:
        node.get_logger().warning(f'could not start building the fusion kernels ahead of time ({exc})')
        return False
    node.get_logger().info(
        f'building the fusion kernels ahead of time: process {process.pid} at the lowest CPU priority (~45 s '
        f'of idle CPU; log {aot_kernels.cache_dir() / aot_background.LOG_NAME}); {meanwhile}; every later '
        'start is warm'
    )
    node.kernel_builder = process
    return True


def _say_warm(node: Any, what: str) -> None:
    """The node's warm line (``graph_events``: a replayer may wait for it before playing)."""
    events = getattr(node, 'events', None)
    if events is not None:
        events.warm(what)


def finish_compiling(node: Any, timeout: float) -> bool:
    """Wait up to ``timeout`` s for a background compilation still running at shutdown; True
    when none is left. (An interpreter that exits while torch compiles on another thread
    aborts in torch's C++ teardown: see :func:`exit_now_if_compiling`.) A thread that only
    waits for the builder process is not compiling: nothing to wait for, the build goes on."""
    thread = getattr(node, 'compile_thread', None)
    if thread is None or not thread.is_alive():
        return True
    if getattr(node, 'waiting_for_builder', False):  # the build goes on in its own process
        return True
    if timeout > 0:
        node.get_logger().info(f'waiting up to {timeout:g} s for the background compilation to end')
        thread.join(timeout)
    return not thread.is_alive()


def compiling() -> bool:
    """Whether a background compilation is still running in this process."""
    return any(t.name == COMPILE_THREAD and t.is_alive() for t in threading.enumerate())


def exit_now_if_compiling(code: int) -> int:
    """A node process about to exit while a compilation still runs ends here, skipping the
    interpreter's teardown (which would abort with a torch error and exit 134); the node was
    destroyed and rclpy shut down already, so nothing is lost."""
    if compiling():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code
