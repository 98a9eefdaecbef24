"""What the processing nodes share: common parameters, counters, the worker (their console
entry point, ``main``, is console.py).

Construction contract (what ``depth-fusion run`` relies on to compose nodes): each node
class takes ``**kwargs`` that go straight to ``rclpy.node.Node`` (``parameter_overrides``,
``cli_args`` with remappings, ``namespace``, ``context``), so the same class runs alone
(``main``) or with the others in one executor. Parameters are validated in the constructor:
a bad value raises ``ValueError`` naming the node and the parameter.

Topic names are relative (``depth_fusion/fused/depth``), so in the root namespace they are
the documented ``/depth_fusion/...`` names and a ``namespace`` moves the whole graph.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from ..data import messages
from . import diagnostics as diag
from .graph_events import GraphEvents
from .input_watch import InputWatch
from .params import ParamSpec, declare_parameters
from .qos import QOS_CHOICES, qos_profile
from .stamp_guard import StampGuard
from .stats import NodeStats
from .worker import POLICIES, BoundedWorker

#: Parameters every processing node declares (before its own).
COMMON_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'input_qos',
        'reliable',
        'QoS of the subscriptions: reliable, or sensor_data (best effort) to match a camera driver',
        choices=QOS_CHOICES,
    ),
    ParamSpec(
        'output_qos',
        'reliable',
        'QoS of the publishers (a reliable publisher also serves best-effort subscribers)',
        choices=QOS_CHOICES,
    ),
    ParamSpec('qos_depth', 10, 'history depth (KEEP_LAST) of every subscription and publisher', 1, 1000),
    # Four, in every node: a keyframe waiting costs little (the multi-view node's feed computes a
    # queued keyframe's estimate anyway; a completed pairing holds two nodes' work), and one slot
    # lost keyframes live (docs/performance.md, "A four-keyframe queue in the multi-view node").
    ParamSpec(
        'queue_size',
        4,
        'work items waiting for the worker thread; more are dropped by queue_policy (memory stays bounded)',
        1,
        100,
    ),
    ParamSpec(
        'queue_policy',
        'latest',
        'when the work queue is full: latest (drop the oldest waiting item), drop_new (drop the new '
        'one) or block (the callback waits: nothing lost, the input is slowed)',
        choices=POLICIES,
    ),
    ParamSpec(
        'stream_restart_jump',
        1.0,
        'an input stamp this many seconds older than the previous one begins a new stream (a bag '
        'played again, a restarted client): the node starts over instead of dropping it as out of '
        'order (0: never)',
        0.0,
        None,
    ),
    ParamSpec('stats_period', 10.0, 'seconds between counter log lines (0: only at shutdown)', 0.0, 86400.0),
    ParamSpec(
        'warn_throttle', 5.0, 'minimum seconds between two warnings for the same drop reason', 0.0, 3600.0
    ),
    *diag.PARAMETERS,
)

#: Input restarts closer together than this (s) are counted as one new stream.
RESTART_NOTE_GAP = 2.0

#: Seconds between two looks at the number of publishers of each input topic.
PUBLISHER_CHECK_PERIOD = 2.0


class DepthFusionNode(Node):
    """An rclpy node with validated parameters, counters, a bounded worker and clean shutdown."""

    #: The node's keyframe events and ready line (graph_events.py), for the nodes that have them.
    events: GraphEvents | None = None

    def __init__(self, node_name: str, specs: Sequence[ParamSpec], **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.params = declare_parameters(self, [*COMMON_PARAMETERS, *specs])
        self.stats = NodeStats(self.get_logger().warning, throttle=float(self.params['warn_throttle']))
        self.input_qos = qos_profile(str(self.params['input_qos']), int(self.params['qos_depth']))
        self.output_qos = qos_profile(str(self.params['output_qos']), int(self.params['qos_depth']))
        self._workers: list[BoundedWorker] = []
        self._last_restart_note = -float('inf')  # note_stream_restart: one note per new stream
        self._destroyed = False
        period = float(self.params['stats_period'])
        if period > 0:
            self.create_wall_timer(period, self.log_stats)
        self.input_watch = InputWatch(self.get_logger().warning)
        self._input_topics: list[str] = []
        self.create_wall_timer(PUBLISHER_CHECK_PERIOD, self._check_publishers)
        self.diagnostics = diag.Diagnostics(
            node_name,
            str(self.params.get('device', 'cpu')),
            float(self.params['diagnostics_drop_share']),
            float(self.params['diagnostics_input_timeout']),
        )
        self._diagnostics_pub = None
        if float(self.params['diagnostics_period']) > 0:
            self._diagnostics_pub = self.create_publisher(
                DiagnosticArray, diag.TOPIC_DIAGNOSTICS, qos_profile('reliable', 10)
            )
            self.create_wall_timer(float(self.params['diagnostics_period']), self.publish_diagnostics)

    def stamp_guard(self, stream: str) -> StampGuard:
        """A :class:`StampGuard` for ``stream`` that takes a jump back of
        ``stream_restart_jump`` seconds for a new stream."""
        return StampGuard(stream, float(self.params['stream_restart_jump']))

    def note_stream_restart(self, stream: str, stamp_ns: int, what: str) -> None:
        """Count (note ``stream_restart``, with its throttled warning) that ``stream`` began again.

        The inputs of one new stream restart one after the other (image, pose, each keyframe
        part): restarts within ``RESTART_NOTE_GAP`` seconds of the first are one restart.
        """
        now = time.monotonic()
        if now - self._last_restart_note < RESTART_NOTE_GAP:
            return
        self._last_restart_note = now
        message = (
            f'{stream} stamps jumped back to {messages.ns_to_sec(stamp_ns):.3f} s: a new stream (a bag '
            f'played again, a restarted client); {what}'
        )
        self.stats.noted('stream_restart', message)

    def subscribe_input(self, msg_type: type, topic: str, callback: Callable[[Any], None], qos: Any) -> Any:
        """:meth:`subscribe` for an input from outside the graph (a camera, a SLAM): made again
        best effort if a best-effort publisher cannot match it (reliability.py). Returns the
        :class:`~.reliability.FollowsBestEffort` holding the subscription."""
        from .reliability import FollowsBestEffort

        return FollowsBestEffort(
            self, topic, qos, lambda q, events: self.subscribe(msg_type, topic, callback, q, events)
        )

    def subscribe(
        self,
        msg_type: type,
        topic: str,
        callback: Callable[[Any], None],
        qos: Any,
        event_callbacks: Any = None,
    ) -> Any:
        """``create_subscription`` whose callback can never take the node down.

        An exception escaping a callback ends ``spin`` and so the node. Every expected problem
        is an ``InputError`` handled in the callback; anything else (a bug, a message nobody
        thought of) is counted as ``callback_error`` and logged with its traceback instead.
        """

        self._input_topics.append(topic)
        resolved = self.resolve_topic_name(topic)

        def guarded(msg: Any) -> None:
            try:
                self.input_watch.observe(resolved, msg)
                callback(msg)
            except Exception as exc:
                self.stats.dropped('callback_error', f'{topic}: {type(exc).__name__}: {exc}')
                self.get_logger().debug(traceback.format_exc())

        return self.create_subscription(msg_type, topic, guarded, qos, event_callbacks=event_callbacks)

    def create_wall_timer(self, period: float, callback: Callable[[], None]) -> Any:
        """A timer on the steady clock: with ``use_sim_time`` a paused or finished bag stops ROS
        time, and counters and pairing timeouts must keep running regardless."""

        def guarded() -> None:
            try:
                callback()
            except Exception as exc:  # same rule as subscriptions: never end the spin
                self.stats.dropped('callback_error', f'timer: {type(exc).__name__}: {exc}')
                self.get_logger().debug(traceback.format_exc())

        return self.create_timer(period, guarded, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def make_worker(
        self,
        name: str,
        handle: Callable[[Any], None],
        on_lost: Callable[[Any, str], None] | None = None,
        start: Callable[[], None] | None = None,
    ) -> BoundedWorker:
        """A worker with this node's queue parameters; drops and failures are counted and logged.

        ``on_lost(item, reason)`` is told of every item dropped (``worker_queue_full`` ...) or
        failed (``processing_error``), e.g. to announce a lost keyframe to the graph. ``start``
        runs first on the worker's thread (a warm-up: :class:`BoundedWorker`).
        """
        lost = on_lost or (lambda item, reason: None)

        def on_drop(item: Any, reason: str) -> None:
            self.stats.dropped(f'worker_{reason}', f'{name} work item dropped ({reason.replace("_", " ")})')
            lost(item, f'worker_{reason}')

        def on_error(item: Any, exc: BaseException) -> None:
            self.stats.dropped('processing_error', f'{name} failed: {type(exc).__name__}: {exc}')
            lost(item, 'processing_error')
            trace = ''.join(traceback.format_exception(type(exc), exc, exc.__traceback__))
            self.get_logger().debug(f'{name} failure:\n{trace}')

        worker = BoundedWorker(
            name,
            handle,
            maxsize=int(self.params['queue_size']),
            policy=str(self.params['queue_policy']),
            on_drop=on_drop,
            on_error=on_error,
            start=start,
        )
        self._workers.append(worker)
        return worker

    def log_stats(self) -> None:
        self.get_logger().info(self.stats.snapshot().summary())

    # --- health: hooks a node overrides, diagnostics, mixed sources ----------------------------------

    def diagnostic_requirements(self) -> list[diag.Requirement]:
        """Inputs that must keep arriving while others do (ERROR in the diagnostics otherwise)."""
        return []

    def readiness(self) -> tuple[bool, str]:
        """``(ready, what it still waits for)``: e.g. no camera_info yet."""
        return True, ''

    def diagnostic_extra(self) -> dict[str, Any]:
        """Node-specific key/values of the diagnostic status."""
        return {}

    def held_items(self) -> int:
        """Inputs held outside the workers that may still become work (images waiting for a pose)."""
        return 0

    def queue_depth(self) -> int:
        return sum(w.pending for w in self._workers)

    def diagnostic_array(self) -> DiagnosticArray:
        """The node's ``DiagnosticArray`` now (also what :meth:`publish_diagnostics` sends)."""
        ready, waiting_for = self.readiness()
        extra = {'held inputs': self.held_items(), **self.diagnostic_extra()}
        return self.diagnostics.array(
            self.get_clock().now().to_msg(),
            self.stats.snapshot(),
            self.stats.arrival_times(),
            self.diagnostic_requirements(),
            self.queue_depth(),
            ready,
            waiting_for,
            extra,
            warnings=list(self.input_watch.findings.values()),
        )

    def publish_diagnostics(self) -> None:
        if self._diagnostics_pub is not None:
            self._diagnostics_pub.publish(self.diagnostic_array())

    def _check_publishers(self) -> None:
        self.input_watch.check_publishers(self, list(dict.fromkeys(self._input_topics)))

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until every worker has nothing queued or in hand and no input is held (tests,
        graceful flushing: images waiting for a pose are not done yet)."""
        deadline = time.monotonic() + timeout
        while self.held_items() and time.monotonic() < deadline:
            time.sleep(0.02)
        if self.held_items():
            return False
        return all(w.wait_idle(max(0.0, deadline - time.monotonic())) for w in self._workers)

    def destroy_node(self) -> None:
        """Stop the workers (finishing the item in hand), log the final counters, then destroy."""
        if not self._destroyed:
            self._destroyed = True
            for worker in self._workers:
                if not worker.stop(timeout=10.0):
                    self.get_logger().warning(f'worker {worker.name} did not stop within 10 s')
            self.close_threads()
            if self.events is not None:
                self.events.close()
            self.get_logger().info(f'final counters: {self.stats.snapshot().summary()}')
        super().destroy_node()

    def close_threads(self) -> None:
        """Stop the node's own threads that publish (besides its workers). Called once, after
        the workers stopped (an item in hand may still need them) and before the publishers
        go: a thread that publishes after that raises in rclpy (``InvalidHandle``)."""
