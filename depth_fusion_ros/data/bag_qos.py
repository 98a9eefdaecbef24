"""The QoS a rosbag2 topic was offered with: recorded with the bag, honoured on replay.

Why: a latched topic (transient local durability: ``/tf_static``, our
``depth_fusion/posing/*``) is subscribed transient local by the nodes that read it, and DDS
does not match a transient-local subscription with a volatile publisher. ``ros2 bag record``
stores each topic's offered QoS in the bag's metadata and ``ros2 bag play`` publishes a topic
that was offered transient local the same way; the recorder and the replayer do as they do, so
a recording of a run can be replayed into a late ``map_node`` and it hears the posings. No ROS
import: the profiles are rosbags' own.
"""

from __future__ import annotations

from typing import Any

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

_NEVER = QosTime(0, 0)


def latched_bag_qos(depth: int) -> Qos:
    """The offered profile of a reliable, transient-local topic keeping its last ``depth``."""
    return Qos(
        QosHistory.KEEP_LAST,
        depth,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        _NEVER,
        _NEVER,
        QosLiveliness.AUTOMATIC,
        _NEVER,
        False,
    )


def recorded_latched_depth(connection: Any) -> int:
    """How many messages a topic's publishers kept for late joiners, as the bag recorded it:
    0 unless every recorded profile of ``connection`` is transient local (a topic with one
    volatile publisher among them is not latched; neither is a bag that recorded no QoS, such
    as a ROS 1 bag or one written by ``convert``)."""
    profiles = list(getattr(getattr(connection, 'ext', None), 'offered_qos_profiles', None) or ())
    if not profiles or any(p.durability != QosDurability.TRANSIENT_LOCAL for p in profiles):
        return 0
    return max(1, max(int(p.depth) for p in profiles))
