"""Messages recorded at the same instant put in the order a node needs them: calibration first.

Why: a converter or a driver may store an image before the camera_info of the same instant; a
node receiving that image first cannot use it (it has no intrinsics yet) and drops it, which
shifts every later keyframe. The replayer plays each run of equal timestamps reordered, which
leaves playback timing unchanged. No ROS import: it orders rosbags' ``(connection, timestamp,
raw)`` tuples by type name.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any

#: Order of messages recorded at the same instant: what describes an image before the image.
INSTANT_ORDER = {
    'sensor_msgs/msg/CameraInfo': 0,
    'geometry_msgs/msg/PoseStamped': 1,
    'geometry_msgs/msg/PoseWithCovarianceStamped': 1,
    'nav_msgs/msg/Odometry': 1,
    'geometry_msgs/msg/TransformStamped': 1,
    'tf2_msgs/msg/TFMessage': 1,
}


def calibration_first(
    messages: Iterable[tuple[Any, int, Any]], msgtype_of: Callable[[Any], str]
) -> Iterator[tuple[Any, int, Any]]:
    """``messages`` with each run of equal timestamps reordered camera_info, poses, then the rest.

    A converter or a driver may store an image before the camera_info of the same instant; a
    node receiving that image first cannot use it (it has no intrinsics yet) and drops it, which
    shifts every later keyframe. Playback timing is unchanged (same timestamps).
    """
    group: list[tuple[Any, int, Any]] = []
    for item in messages:
        if group and item[1] != group[0][1]:
            yield from sorted(group, key=lambda m: INSTANT_ORDER.get(msgtype_of(m[0]), 2))
            group = []
        group.append(item)
    yield from sorted(group, key=lambda m: INSTANT_ORDER.get(msgtype_of(m[0]), 2))
