"""Inputs that follow a best-effort publisher instead of never matching it.

A reliable subscription does not match a best-effort publisher (DDS: the offered reliability
must be at least the requested one). Camera drivers, and many clients, publish images with
``qos_profile_sensor_data`` (best effort); with the nodes' default ``input_qos: reliable`` such
a topic delivered nothing, and the only sign was rmw's warning about an incompatible QoS. A
best-effort subscription matches both kinds but gives up the repair of lost samples, so the
nodes keep asking for reliable delivery and step down only when a publisher cannot give it:
on the incompatible-QoS event (reliability) of an input subscription, it is made again best
effort, once, with a warning and a counted note (``qos_best_effort``).

The swap runs on a timer, not in the event callback: the event belongs to the subscription
being replaced. The replaced subscription is not destroyed while the node spins, only made
inert (its callback discards): destroying it also destroys its QoS event handler, which an
executor may still hold from the wait set it is iterating, and rclpy then raises
``InvalidHandle`` out of ``spin`` and the node stops for good (seen under load: the graph
received nothing after the first step down). An inert reliable subscription matches only
reliable publishers: on a topic that has both kinds, their samples are taken there and
discarded (the best-effort subscription delivers them once). The retired subscriptions are
destroyed with the input (:meth:`FollowsBestEffort.close`).

The event can also fail to come (discovery under load), so the graph is also looked at every
``GRAPH_CHECK_PERIOD`` seconds: a best-effort publisher listed on the topic steps the input
down the same way.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import QoSPolicyKind, QoSProfile, ReliabilityPolicy

#: seconds between looks for subscriptions to step down (the swap's timer)
SWAP_PERIOD = 0.2
#: seconds between looks at the topic's publishers, in case the incompatible-QoS event is lost
GRAPH_CHECK_PERIOD = 1.0


def best_effort(qos: QoSProfile) -> QoSProfile:
    """``qos`` with best-effort reliability (history, depth and durability kept)."""
    return QoSProfile(
        history=qos.history,
        depth=qos.depth,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=qos.durability,
    )


def ignore_incompatible() -> SubscriptionEventCallbacks:
    """Event callbacks that say nothing about an incompatible publisher (a subscription that
    is meant to match only some publishers, e.g. the latched twin of a volatile one)."""
    return SubscriptionEventCallbacks(incompatible_qos=lambda status: None)


class FollowsBestEffort:
    """Watches one input subscription and makes it again best effort when a best-effort
    publisher cannot match it.

    ``make(qos, event_callbacks)`` creates the subscription (and returns it); a step down
    destroys the current subscription and calls ``make`` again with best-effort QoS.
    """

    def __init__(
        self,
        node: Any,
        topic: str,
        qos: QoSProfile,
        make: Callable[[QoSProfile, SubscriptionEventCallbacks], Any],
    ) -> None:
        self.node = node
        self.topic = topic
        self.qos = qos
        self._make = make
        #: the one-shot timer of a pending step down (none while nothing is incompatible)
        self._timer: Any = None
        self.subscription = make(qos, self.event_callbacks())
        #: replaced subscriptions, inert until ``close`` (see the module docstring)
        self._retired: list[Any] = []
        #: the periodic look at the topic's publishers (while the input is still reliable)
        self._graph_timer: Any = (
            node.create_wall_timer(GRAPH_CHECK_PERIOD, self._check_graph) if self.reliable else None
        )

    @property
    def reliable(self) -> bool:
        return self.qos.reliability == ReliabilityPolicy.RELIABLE

    def event_callbacks(self) -> SubscriptionEventCallbacks:
        return SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible)

    def _on_incompatible(self, status: Any) -> None:
        if status.last_policy_kind == QoSPolicyKind.RELIABILITY:
            self._step_down_soon()

    def _check_graph(self) -> None:
        """Step down when a publisher of the topic offers best effort only (the graph says so
        even when the incompatible-QoS event never came)."""
        try:
            infos = self.node.get_publishers_info_by_topic(self.node.resolve_topic_name(self.topic))
        except Exception:  # a graph query failing is no reason to stop the node
            return
        if any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
            self._step_down_soon()

    def _step_down_soon(self) -> None:
        """Schedule the swap (once; both triggers end here), off the caller's callback."""
        if self.reliable and self._timer is None:
            self._timer = self.node.create_wall_timer(SWAP_PERIOD, self._swap)

    def _stop_timers(self) -> None:
        """Destroy the pending swap and the graph look (a best-effort input needs neither)."""
        for timer in (self._timer, self._graph_timer):
            if timer is not None:
                timer.cancel()
                self.node.destroy_timer(timer)
        self._timer = self._graph_timer = None

    def _swap(self) -> None:
        self._stop_timers()
        self.subscription.callback = _discard  # inert, not destroyed (module docstring)
        self._retired.append(self.subscription)
        self.qos = best_effort(self.qos)
        self.subscription = self._make(self.qos, self.event_callbacks())
        message = (
            f'{self.node.resolve_topic_name(self.topic)}: a publisher offers best effort only, which a '
            'reliable subscription never matches; subscribed best effort (input_qos: sensor_data does '
            'so from the start)'
        )
        self.node.stats.noted('qos_best_effort', message)

    def close(self) -> None:
        """Destroy the subscription, the ones it replaced and a pending step down."""
        self._stop_timers()
        for subscription in (*self._retired, self.subscription):
            self.node.destroy_subscription(subscription)
        self._retired.clear()


def _discard(msg: Any) -> None:
    """The callback of a replaced subscription: nothing arrives there twice."""
