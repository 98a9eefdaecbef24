"""Latched announcements: a node's fixed facts (the single-view output kind, the multi-view
method) that every subscriber must hear, whenever it joins.

Transient-local durability alone should do it, but with Fast DDS a late-joining reader
intermittently misses the writer's historical sample (eProsima/Fast-DDS#3822, open: 5-10 %
in its reproducer; our late-joiner node test failed so once under load). A fusion node that
missed the output kind would treat a relative model's depth as metric, silently. So the
value is also published again each time a new subscription matches the publisher (the
``matched`` event): a reader that got the historical sample hears the same value twice,
which the receivers treat as the no-op it is.
"""

from __future__ import annotations

from rclpy.event_handler import PublisherEventCallbacks, QoSPublisherMatchedInfo
from rclpy.node import Node
from rclpy.publisher import Publisher
from std_msgs.msg import String

from .qos import latched_qos


def announce(node: Node, topic: str, value: str) -> Publisher:
    """Publish ``value`` on ``topic`` (latched), and again to every subscription that matches later."""
    message = String(data=value)
    publisher: list[Publisher] = []

    def on_matched(info: QoSPublisherMatchedInfo) -> None:
        if info.current_count_change > 0 and publisher:
            publisher[0].publish(message)

    callbacks = PublisherEventCallbacks(matched=on_matched)
    publisher.append(node.create_publisher(String, topic, latched_qos(), event_callbacks=callbacks))
    publisher[0].publish(message)
    return publisher[0]
