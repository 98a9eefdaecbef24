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
(``depth-fusion run`` without ``--processes``, several nodes and executors in one process)
keeps its single-threaded executors: there, an events executor per node spun both cores at
100 % and did not stop on SIGTERM (tried 2026-11-28; not investigated further).
"""

from __future__ import annotations

import os
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


def make_node_executor(choice: str) -> tuple[Any, str]:
    """The executor for ``choice`` in rclpy's default context, and the line to log. Falls back
    to the single-threaded one (said in the line) where this rclpy has no events executor (a
    ROS install older than Jazzy's rclpy 7.1.4, not the pinned wheels)."""
    from rclpy.executors import SingleThreadedExecutor

    if choice == 'events':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            why = f'this rclpy has no rclpy.experimental.EventsExecutor; {ENV}=events ignored'
            return SingleThreadedExecutor(), f'executor: single-threaded ({why})'
        line = f'executor: events (rclpy.experimental; {ENV}=single: single-threaded)'
        return EventsExecutor(), line
    return SingleThreadedExecutor(), f'executor: single-threaded ({ENV}=single)'
