"""FollowsBestEffort without DDS: the graph look steps an input down when the event never came,
and the replaced subscription is made inert, not destroyed, until the input closes."""

from __future__ import annotations

from types import SimpleNamespace

from rclpy.qos import QoSProfile, ReliabilityPolicy

from depth_fusion_ros.nodes.reliability import FollowsBestEffort


class _Timer:
    def __init__(self, period: float, callback) -> None:
        self.period, self.callback, self.cancelled = period, callback, False

    def cancel(self) -> None:
        self.cancelled = True


class _Node:
    """What FollowsBestEffort uses of a node, with a scripted publisher list."""

    def __init__(self, publishers: list[ReliabilityPolicy]) -> None:
        self.publishers = publishers
        self.timers: list[_Timer] = []
        self.notes: list[str] = []
        self.destroyed: list = []
        self.stats = SimpleNamespace(noted=lambda reason, message: self.notes.append(reason))

    def create_wall_timer(self, period: float, callback) -> _Timer:
        self.timers.append(_Timer(period, callback))
        return self.timers[-1]

    def destroy_timer(self, timer: _Timer) -> None:
        self.timers.remove(timer)

    def destroy_subscription(self, subscription) -> None:
        self.destroyed.append(subscription)

    def resolve_topic_name(self, topic: str) -> str:
        return '/' + topic

    def get_publishers_info_by_topic(self, topic: str) -> list:
        return [SimpleNamespace(qos_profile=QoSProfile(depth=1, reliability=r)) for r in self.publishers]


def test_the_graph_steps_an_input_down_when_the_event_is_lost():
    node = _Node([ReliabilityPolicy.RELIABLE])
    made: list[QoSProfile] = []
    subscriptions: list[SimpleNamespace] = []

    def make(qos: QoSProfile, events) -> SimpleNamespace:
        made.append(qos)
        subscriptions.append(SimpleNamespace(qos=qos, callback=lambda msg: None))
        return subscriptions[-1]

    follow = FollowsBestEffort(node, 'camera/image', QoSProfile(depth=5), make)
    (graph,) = node.timers
    graph.callback()  # a reliable publisher only: nothing to do
    assert follow.reliable and len(node.timers) == 1 and node.notes == []
    node.publishers.append(ReliabilityPolicy.BEST_EFFORT)  # a sensor-data publisher appears
    graph.callback()
    swap = node.timers[-1]
    swap.callback()  # the step down, as the event path does it
    assert not follow.reliable and made[-1].reliability == ReliabilityPolicy.BEST_EFFORT
    assert node.notes == ['qos_best_effort'] and node.timers == []  # once, and nothing left polling
    # The replaced subscription is inert, not destroyed: an executor may still hold its QoS
    # event handler (destroyed, rclpy raised InvalidHandle out of spin); it goes at close.
    old, new = subscriptions
    assert node.destroyed == [] and follow.subscription is new and old.callback('msg') is None
    follow.close()
    assert node.destroyed == [old, new]
    best = FollowsBestEffort(node, 'x', made[-1], make)
    assert best._graph_timer is None and node.timers == []  # already best effort: no look
