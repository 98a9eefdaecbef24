"""An isolated rclpy context with a background executor: run nodes in-process over real DDS.

Tests (and the graph runner's tests) start the nodes in the same process as the test, in
their own :class:`rclpy.context.Context`, spun by a ``MultiThreadedExecutor`` on a
background thread, and talk to them through a helper node in the same context. Messages
still go through DDS (rclpy has no intra-process shortcut), so this exercises the real
transport without the seconds-long start-up of a subprocess per node.

Each harness takes a **ROS domain of its own** (a free one of :data:`TEST_DOMAINS`, locked and
probed as ``depth-fusion run`` picks its domain, held until :meth:`RosHarness.close`), so
a participant another test left behind, still shutting down, or a second test run on the
same machine cannot publish into it: latched topics (an announced output kind, a ready
line) from elsewhere would otherwise reach the nodes under test as soon as discovery finds
them, which with the package's 0.5 s announcements is well within a test.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions

from .graph.isolation import pick_free_domain
from .qos import qos_profile

log = logging.getLogger(__name__)

#: Domains a harness picks from: the test suite's range (``depth-fusion run`` takes 101 and
#: 215-232, graph/isolation.py).
TEST_DOMAINS = tuple(range(1, 101))


class RosHarness:
    """A context + executor thread + a ``probe`` node that publishes inputs and collects outputs."""

    def __init__(
        self, args: Sequence[str] | None = None, threads: int = 4, domain_id: int | None = None
    ) -> None:
        """``domain_id``: join that domain (e.g. to meet node processes) instead of a private one."""
        self._domain_lock = None
        if domain_id is None:
            domain_id, self._domain_lock = pick_free_domain(TEST_DOMAINS)
        self.domain_id = domain_id
        self.context = Context()
        rclpy.init(
            args=list(args) if args else None,
            context=self.context,
            domain_id=domain_id,
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.executor = MultiThreadedExecutor(num_threads=threads, context=self.context)
        self.probe = Node('test_probe', context=self.context)
        self.executor.add_node(self.probe)
        self._nodes: list[Node] = [self.probe]
        self._thread = threading.Thread(target=self._spin, name='ros-harness', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        # The context is shut down while spinning when the harness closes: expected, logged at
        # debug. Anything else that stops the executor would leave a test waiting on a dead
        # graph, so it is printed with its traceback.
        try:
            self.executor.spin()
        except Exception:
            if self.context.ok():
                log.exception('the test harness executor stopped; the graph no longer spins')
            else:
                log.debug('the test harness executor stopped with its context', exc_info=True)

    def add(self, node: Node) -> Node:
        """Spin ``node`` (created with ``context=harness.context``) on the harness executor."""
        self._nodes.append(node)
        self.executor.add_node(node)
        return node

    def publisher(self, msg_type: type, topic: str, qos: QoSProfile | None = None) -> Any:
        return self.probe.create_publisher(msg_type, topic, qos or qos_profile('reliable', 10))

    def collect(self, msg_type: type, topic: str, qos: QoSProfile | None = None) -> list[Any]:
        """A list that receives every message published on ``topic`` (appended by the executor)."""
        received: list[Any] = []
        self.probe.create_subscription(msg_type, topic, received.append, qos or qos_profile('reliable', 10))
        return received

    @staticmethod
    def wait_for(predicate: Callable[[], bool], timeout: float = 10.0, period: float = 0.01) -> bool:
        """Poll ``predicate`` until it is true (``True``) or ``timeout`` seconds pass (``False``)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(period)
        return bool(predicate())

    @staticmethod
    def wait_until_stable(value: Callable[[], Any], quiet: float = 0.5, timeout: float = 10.0) -> Any:
        """Poll ``value()`` until it has not changed for ``quiet`` seconds; return it.

        For floods, where KEEP_LAST histories may legitimately lose part of a burst and the test
        cannot know how many messages will arrive.
        """
        deadline = time.monotonic() + timeout
        last, since = value(), time.monotonic()
        while time.monotonic() < deadline:
            time.sleep(0.05)
            current = value()
            if current != last:
                last, since = current, time.monotonic()
            elif time.monotonic() - since >= quiet:
                break
        return last

    def wait_for_subscribers(self, publishers: Sequence[Any], count: int = 1, timeout: float = 10.0) -> bool:
        """Wait until every publisher is matched by ``count`` subscriptions (DDS discovery)."""
        return self.wait_for(lambda: all(p.get_subscription_count() >= count for p in publishers), timeout)

    def close(self) -> None:
        """Destroy every node (stopping their workers), stop the executor, shut the context down."""
        for node in reversed(self._nodes):
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=5.0)
        self.context.try_shutdown()
        self._thread.join(5.0)
        if self._domain_lock is not None:
            self._domain_lock.close()
            self._domain_lock = None

    def __enter__(self) -> RosHarness:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
