"""The executor a console node (one node per process) spins: rclpy's events executor.

Why: rclpy's default ``SingleThreadedExecutor`` rebuilds its wait set in Python on every
wake-up (``_wait_for_ready_callbacks``: each subscription, timer, service and guard
condition re-added, ``can_execute`` asked of each), and a camera node wakes 90 times a
second at 30 Hz (image, camera_info, pose). Measured on the live 7-Scenes stream (2 cores,
docs/performance.md "The events executor"): the multi-view node's executor thread used 3.2 s
of CPU over the stream, 1.2-1.9 s with ``rclpy.experimental.EventsExecutor``, whose queue of
ready events is kept in C++; the three nodes saved about 0.18 of a core between them.

The events executor is in rclpy since Jazzy 7.1.4 (backported from Rolling) and still in
``rclpy.experimental``. ``DEPTH_FUSION_EXECUTOR=single`` gives the
``SingleThreadedExecutor`` back (a one-line log says which one runs). The composed graph
(``depth-fusion run`` without ``--processes``) gives each node an executor of the same
choice, in its own thread, and the console ``bag_replayer`` and recorder spin one too: the
replayer's pacer hears the graph's events several times a keyframe, and with the
single-threaded executor it took 21-30 ms of CPU a fused keyframe flat out, 14-22 ms with this
one in the same hours (docs/performance.md, "The replayer's executor").

Spin it with :func:`spin_until`, never with ``spin()``: this rclpy's
``EventsExecutor.spin()`` waits in C++ while holding the GIL, so it runs one core at 100 %,
starves the process's other Python threads and never returns to notice a stop (measured:
one idle node, one core busy; SIGTERM ignored). ``spin_once`` with a timeout waits without
the GIL (four nodes, 400 messages/s: 0.12 of a core, against 0.36 with four
single-threaded executors).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

#: Environment variable that chooses the console nodes' executor: ``events`` (default) or ``single``.
ENV = 'DEPTH_FUSION_EXECUTOR'
CHOICES = ('events', 'single')


def executor_choice() -> str:
    """``events`` or ``single`` from :data:`ENV`; ``ValueError`` naming the variable otherwise."""
    value = os.environ.get(ENV, 'events').strip().lower() or 'events'
    if value not in CHOICES:
        raise ValueError(f'{ENV}={value!r}: must be one of {", ".join(CHOICES)}')
    return value


def make_node_executor(choice: str, context: Any = None) -> tuple[Any, str]:
    """The executor for ``choice`` in ``context`` (rclpy's default one when None), and the line
    to log. Falls back to the single-threaded one (said in the line) where this rclpy has no
    events executor (a ROS install older than Jazzy's rclpy 7.1.4, not the pinned wheels)."""
    from rclpy.executors import SingleThreadedExecutor

    if choice == 'events':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            why = f'this rclpy has no rclpy.experimental.EventsExecutor; {ENV}=events ignored'
            return SingleThreadedExecutor(context=context), f'executor: single-threaded ({why})'
        line = f'executor: events (rclpy.experimental; {ENV}=single: single-threaded)'
        return EventsExecutor(context=context), line
    return SingleThreadedExecutor(context=context), f'executor: single-threaded ({ENV}=single)'


def spin_until(executor: Any, running: Callable[[], bool], timeout_sec: float = 0.2) -> None:
    """Spin ``executor`` one callback at a time while ``running()`` says so. Each wait ends after
    ``timeout_sec`` at the latest, so a stop is noticed within that; the wait itself does not
    hold the GIL (unlike ``EventsExecutor.spin()``, module docstring)."""
    while running():
        executor.spin_once(timeout_sec=timeout_sec)
