"""QoS profiles of the node graph, chosen by a parameter instead of hard-coded per topic.

Two families matter here:

* ``reliable`` (the default): every keyframe image and depth reaches the next node. The
  graph publishes a few keyframes per second, so the cost of retransmission is nothing next
  to losing a keyframe the fusion node is waiting for.
* ``sensor_data`` (best effort, volatile): what camera drivers publish with. A reliable
  subscription does not match a best-effort publisher, so a node fed by such a driver must
  be told. Large best-effort images across processes need the Fast DDS shared-memory
  profile (see /work/shared/ROS2_PIP.md), or most are lost.

Latched topics (the single-view output kind) always use ``transient_local`` so a late
subscriber still hears them.
"""

from __future__ import annotations

from typing import Any

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

#: Values accepted by the ``qos`` / ``output_qos`` parameters.
QOS_CHOICES = ('reliable', 'sensor_data')


def qos_profile(kind: str, depth: int) -> QoSProfile:
    """The profile named ``kind`` (one of :data:`QOS_CHOICES`) keeping the last ``depth`` messages."""
    if depth < 1:
        raise ValueError(f'QoS depth must be at least 1, got {depth}')
    if kind == 'reliable':
        reliability = ReliabilityPolicy.RELIABLE
    elif kind == 'sensor_data':
        reliability = ReliabilityPolicy.BEST_EFFORT
    else:
        raise ValueError(f'unknown QoS {kind!r}: expected one of {", ".join(QOS_CHOICES)}')
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=reliability,
        durability=DurabilityPolicy.VOLATILE,
    )


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable, transient-local, keeping the last ``depth`` values (1: the last value) for
    subscribers that join later."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def offers_latched(info: Any) -> bool:
    """Whether a publisher (an entry of ``get_publishers_info_by_topic``) keeps its last samples
    for late joiners (transient local): the test a latched subscription needs, since DDS never
    matches a transient-local reader with a volatile writer."""
    return info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
