"""Latched announcements reach subscribers that join late, even without the DDS history."""

from __future__ import annotations

from rclpy.node import Node
from std_msgs.msg import String

from depth_fusion_ros.nodes.announce import announce
from depth_fusion_ros.nodes.qos import latched_qos, qos_profile
from depth_fusion_ros.nodes.testing import RosHarness


def test_a_late_subscriber_hears_the_value_without_the_historical_sample():
    """A volatile subscriber never gets the transient-local history (what a late joiner gets
    when Fast DDS loses it, eProsima/Fast-DDS#3822): only the value published again on the
    match reaches it. A transient-local one hears the same value (once or twice)."""
    with RosHarness() as ros:
        node = ros.add(Node('announcer', context=ros.context))
        announce(node, '/announce_test/kind', 'inverse_depth')
        volatile = ros.collect(String, '/announce_test/kind', qos_profile('reliable', 1))
        latched = ros.collect(String, '/announce_test/kind', latched_qos())
        assert ros.wait_for(lambda: volatile and latched, 30.0)
        ros.wait_until_stable(lambda: (len(volatile), len(latched)), quiet=0.5, timeout=5.0)
    assert [msg.data for msg in volatile] == ['inverse_depth'] * len(volatile)
    assert {msg.data for msg in latched} == {'inverse_depth'}
