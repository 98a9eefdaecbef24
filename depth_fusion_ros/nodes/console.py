"""A console node's life: signals, rclpy init, one executor, and a stop that never hangs unseen.

Each node's ``main`` (``fusion_node``, ``multi_view_node``, ``single_view_node``, ``map_node``)
is :func:`run_node` with the node's class; ``depth-fusion run --processes`` forks the same
``main`` (graph/forked.py). The composed graph builds the node classes itself
(graph/lifecycle.py) and shares none of this but the stop order.
"""

from __future__ import annotations

import atexit
import faulthandler
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node

from ..malloc_tuning import keep_freed_memory
from .gil import set_switch_interval
from .graph.dds import profile_for_console_node
from .graph.dds_readers import resolved_topic
from .graph.spawn import STOP_STACKS_AFTER_S
from .node_executor import executor_choice, make_node_executor, spin_until
from .rcl_errors import rcl_message
from .robot_inputs import image_topic_for
from .threads import apply_node_threads


def arm_stop_stacks() -> None:
    """A stop that hangs leaves every thread's stack in the node's log, after
    ``STOP_STACKS_AFTER_S`` (then the graph kills it: graph/spawn.py); without it a hang seen
    once on CI says nothing about where. It stays armed through the interpreter's teardown,
    which joins the threads left (a forked node ends right after that; a console script
    disarms it at exit). Only one such timer exists per process: this replaces any other."""
    faulthandler.dump_traceback_later(STOP_STACKS_AFTER_S, exit=False)
    atexit.unregister(faulthandler.cancel_dump_traceback_later)  # registered once
    atexit.register(faulthandler.cancel_dump_traceback_later)  # runs after the threads were joined


def _close_executor(executor: Any, node: Node) -> None:
    """Take the node out of its executor and shut the executor down, before the node is
    destroyed and rclpy shuts down: the order the composed graph keeps (graph/lifecycle.py),
    rather than leaving the events executor (C++) to be torn down after its context is gone."""
    if executor is None:
        return
    try:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=5.0)
    except Exception as exc:  # the node is destroyed anyway
        node.get_logger().warning(f'closing the executor failed: {exc!r}')


def run_node(
    factory: Callable[[], Node],
    args: Sequence[str] | None = None,
    udp_image_topics: Sequence[str] = (),
    node_name: str = '',
) -> int:
    """Console entry point body: init, build the node, spin until Ctrl-C/SIGTERM, clean up.

    rclpy's own signal handler would shut the context down at once, so the final counters
    could no longer reach ``/rosout``; instead SIGINT and SIGTERM end the spin loop, the node
    is destroyed while the context is still valid (workers joined, final counters logged),
    then rclpy shuts down. The signals set a flag rather than raise: a KeyboardInterrupt that
    lands while the constructor finishes (just after its "ready" line) would leave no node to
    destroy and no final counters. A second Ctrl-C interrupts at once (a constructor that
    hangs). Returns the process exit code: 0 on a normal stop, 2 when a parameter is invalid
    (the message names it; no traceback: it is the user's to fix). ``udp_image_topics``: the
    node's camera image topics (as declared, resolved here with the command line's remaps for
    ``node_name``), read over UDP with their ``/compressed`` (graph/dds_readers.py).
    """
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    try:
        set_switch_interval()  # the node's threads hand the GIL over sooner (gil.py)
        choice = executor_choice()  # a bad DEPTH_FUSION_EXECUTOR fails now, in one line
    except ValueError as exc:
        rclpy.logging.get_logger('depth_fusion').error(str(exc))
        return 2
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        if signum == signal.SIGINT and stop.is_set():
            raise KeyboardInterrupt  # the second Ctrl-C
        stop.set()

    previous_term = signal.signal(signal.SIGTERM, on_signal)
    previous_int = signal.signal(signal.SIGINT, on_signal)
    argv = list(sys.argv if args is None else args)
    bases = [resolved_topic(t, node_name, argv) for t in udp_image_topics]
    readers = [name for base in bases for name in (base, image_topic_for(base, 'compressed'))]
    profile_line = profile_for_console_node(udp_readers=readers)  # before rclpy.init: read once
    threads_line = apply_node_threads()
    keep_freed_memory()  # freed tensor memory reused (DEPTH_FUSION_MALLOC_TUNING=0: off), malloc_tuning.py
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except _rclpy.RCLError as exc:  # a bad --ros-args (a remap rcl cannot parse): one line, not a traceback
        rclpy.logging.get_logger('depth_fusion').error(
            f'{node_name or "node"}: cannot start: {rcl_message(exc)}'
        )
        signal.signal(signal.SIGTERM, previous_term)
        signal.signal(signal.SIGINT, previous_int)
        return 2
    rclpy.logging.get_logger('depth_fusion').info(profile_line)
    rclpy.logging.get_logger('depth_fusion').info(threads_line)
    node = None
    executor = None
    code = 0
    try:
        node = factory()
        executor, executor_line = make_node_executor(choice)
        rclpy.logging.get_logger('depth_fusion').info(executor_line)
        executor.add_node(node)
        spin_until(executor, lambda: rclpy.ok() and not stop.is_set())  # notices a signal within 0.2 s
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, FileNotFoundError) as exc:
        rclpy.logging.get_logger('depth_fusion').error(str(exc))
        code = 2
    finally:
        arm_stop_stacks()
        if node is not None:
            _close_executor(executor, node)
            node.destroy_node()
        rclpy.try_shutdown()
        signal.signal(signal.SIGTERM, previous_term)
        signal.signal(signal.SIGINT, previous_int)
    return code
