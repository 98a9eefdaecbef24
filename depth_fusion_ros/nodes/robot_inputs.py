"""The input flavours robots publish: image_transport ``compressed``, four pose message types,
and a pose that is not the camera's.

* ``image_transport: compressed`` subscribes to ``<image topic>/compressed``
  (``sensor_msgs/CompressedImage``) instead of the raw topic; decoding is in
  ``data.compressed`` and happens in the node's image callback like raw decoding.
* ``pose_type`` picks the pose message: ``PoseStamped``, ``PoseWithCovarianceStamped``
  (AMCL-style, some SLAMs), ``nav_msgs/Odometry`` (VINS-Fusion, robot_localization) or
  ``TransformStamped`` (motion-capture bridges such as vicon_bridge, one topic per body: a
  ``/tf`` transform on a topic of its own; ``/tf`` itself needs tf2_msgs, not on pip). ``auto``
  waits for a publisher and subscribes with its type (ROS cannot subscribe "to any type").
* ``pose_inverted`` reads each pose inverted, for a source that publishes the world's pose in
  the camera (T_cw, as a SLAM system keeps it) where ROS means the camera's in the world.
* ``camera_from_pose_frame`` is the fixed transform from the pose's frame (a body or IMU
  frame) to the camera optical frame: ``T_world_cam = T_world_pose @ T_pose_cam``. TF is not
  on pip for Jazzy, so it is a parameter (docs/nodes.md says how to read it from a URDF or
  ``tf2_echo``), read by ``geometry.transform_from_parameter``, as the commands' option of the
  same name is.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from ..data import messages
from ..data.compressed import COMPRESSED_SUFFIX, TRANSPORTS
from .params import ParamSpec

#: ``pose_type`` value -> ROS message type name.
POSE_MESSAGE_TYPES = {
    'pose_stamped': 'geometry_msgs/msg/PoseStamped',
    'pose_with_covariance': 'geometry_msgs/msg/PoseWithCovarianceStamped',
    'odometry': 'nav_msgs/msg/Odometry',
    'transform_stamped': 'geometry_msgs/msg/TransformStamped',
}
POSE_TYPES = ('auto', *POSE_MESSAGE_TYPES)
IDENTITY_TQ = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'image_transport',
        'raw',
        'raw: sensor_msgs/Image on the image topic; compressed: sensor_msgs/CompressedImage (JPEG/PNG) '
        "on '<image topic>/compressed', as image_transport's compressed plugin publishes it",
        choices=TRANSPORTS,
    ),
    ParamSpec(
        'pose_type',
        'auto',
        'message type of the pose topic: pose_stamped, pose_with_covariance (PoseWithCovarianceStamped), '
        'odometry (nav_msgs/Odometry, its pose.pose), transform_stamped (TransformStamped, a motion-capture '
        "bridge's body: child_frame_id in header.frame_id); auto: the type the topic's publishers use",
        choices=POSE_TYPES,
    ),
    ParamSpec(
        'camera_from_pose_frame',
        IDENTITY_TQ,
        "x, y, z, qx, qy, qz, qw: the camera optical frame in the pose's frame (the pose's child frame, "
        "e.g. base_link or imu); T_world_cam = T_world_pose @ this; identity: the pose is the camera's",
        length=7,
    ),
    ParamSpec(
        'pose_inverted',
        False,
        "true: each pose (and corrected trajectory) is the world's pose in the pose frame (T_cw, as "
        "a SLAM system keeps it, e.g. ORB-SLAM's Tcw) and is inverted before use; ROS means the "
        "frame's pose in the world (T_wc). The mount check says when the poses fit the images "
        'inverted (multiview/pose_inversion.py)',
    ),
)


def image_topic_for(topic: str, transport: str) -> str:
    """The topic the images of ``transport`` come on (``<topic>/compressed`` for compressed)."""
    return topic.rstrip('/') + COMPRESSED_SUFFIX if transport == 'compressed' else topic


def image_message_class(transport: str) -> type:
    from sensor_msgs.msg import CompressedImage, Image

    return CompressedImage if transport == 'compressed' else Image


def subscribe_image(node: Any, topic: str, callback: Callable[[Any], None], qos: Any, transport: str) -> str:
    """Subscribe ``callback`` to the images of ``transport``; returns the topic subscribed.

    As image_transport does, the compressed topic hangs off the *resolved* base topic: with
    ``-r camera/rgb/image_color:=/my_cam/image_raw`` the node reads
    ``/my_cam/image_raw/compressed`` (a remap matches whole names, so the relative
    ``camera/rgb/image_color/compressed`` would have stayed where it was).
    """
    name = image_topic_for(node.resolve_topic_name(topic), transport)
    node.subscribe_input(image_message_class(transport), name, callback, qos)
    return name


class TransportCheck:
    """Warns once when the images come on the other transport's topic.

    A graph subscribed to ``/camera/image`` (raw) while the camera publishes only
    ``/camera/image/compressed`` (or the reverse) receives camera_info and poses and no image,
    and would otherwise say nothing but ``received 0``: the most common set-up slip with
    image_transport, whose plugins ROS 2 nodes pick by parameter, not by discovery.
    """

    def __init__(self, node: Any, topic: str, transport: str) -> None:
        self.node = node
        self.topic = topic
        self.transport = transport
        #: the warning once it was given (also listed in the node's diagnostics)
        self.finding: str | None = None

    def check(self) -> None:
        """One look at the publishers of both transports' topics (a timer calls it)."""
        if self.finding is not None:
            return
        base = self.node.resolve_topic_name(self.topic)
        mine = self.node.resolve_topic_name(image_topic_for(base, self.transport))
        if self.node.count_publishers(mine) > 0:
            return
        other_transport = 'raw' if self.transport == 'compressed' else 'compressed'
        other = self.node.resolve_topic_name(image_topic_for(base, other_transport))
        found = self.node.count_publishers(other)
        if found == 0:
            return
        self.finding = (
            f'no publisher on {mine} ({self.transport}) but {found} on {other}: images are '
            f'not received; set image_transport:={other_transport}, or remap the image topic'
        )
        self.node.input_watch.findings[f'{mine} transport'] = self.finding
        self.node.get_logger().warning(self.finding)


def pose_message_class(pose_type: str) -> type:
    return messages.RCLPY.message_class(POSE_MESSAGE_TYPES[pose_type])


def pose_type_of(msgtype: str) -> str | None:
    """``pose_type`` of a ROS type name (``geometry_msgs/msg/PoseStamped``), ``None`` if unsupported."""
    for key, value in POSE_MESSAGE_TYPES.items():
        if value == msgtype:
            return key
    return None


def pose_type_for_topics(topic_types: Mapping[str, str], pose_topic: str = '/camera/pose') -> str:
    """``pose_type`` for a bag or graph whose topics have these types (``{name: 'pkg/msg/Type'}``).

    ``'auto'`` when the pose topic is absent or of an unsupported type (the node then reports
    it); otherwise the explicit type, so a composed graph subscribes with it from the start.
    """
    return pose_type_of(str(topic_types.get(pose_topic, ''))) or 'auto'


class PoseSubscription:
    """Subscribes to the pose topic with the configured type, or discovers it (``auto``).

    ``auto`` subscribes at once as PoseStamped (the common case: no pose is lost while the
    graph starts, and a replayer waiting for its subscribers sees one), then polls the topic's
    publishers (``get_publishers_info_by_topic``) on a timer and, when they use another
    supported type, subscribes with that type instead. Publishers of several pose types (two
    pose sources on one topic) are warned about once; a publisher of an unsupported type too.
    """

    #: In one process (one DDS participant) a topic has one type: a node composed with a
    #: publisher of another pose type created *after* it must be given ``pose_type`` explicitly
    #: (``depth-fusion run`` does, from the bag: :func:`pose_type_for_topics`).
    PROVISIONAL = 'pose_stamped'
    #: seconds between two looks at the publishers once the type is known (conflict watch only)
    SLOW_PERIOD = 2.0

    def __init__(
        self, node: Any, topic: str, pose_type: str, callback: Callable[[Any], None], qos: Any,
        period: float = 0.25,
    ) -> None:  # fmt: skip
        self.node = node
        self.topic = topic
        self.callback = callback
        self.qos = qos
        #: the type confirmed by a publisher (or configured); None while ``auto`` has seen none
        self.pose_type: str | None = None
        #: the type of the current subscription
        self.subscribed_type: str | None = None
        self._subscription: Any = None
        self._warned: set[str] = set()
        self._timer: Any = None
        if pose_type == 'auto':
            try:
                self._subscribe(self.PROVISIONAL)
            except Exception as exc:  # another type is already on the topic in this process
                node.get_logger().debug(f'no provisional PoseStamped subscription: {exc}')
            self._timer = node.create_wall_timer(period, self.discover)
        else:
            self.pose_type = pose_type
            self._subscribe(pose_type)

    @property
    def resolved_topic(self) -> str:
        return self.node.resolve_topic_name(self.topic)

    @property
    def description(self) -> str:
        """For diagnostics: the confirmed type, or the provisional one."""
        return self.pose_type or f'{self.subscribed_type} (auto: no publisher seen yet)'

    def _subscribe(self, pose_type: str) -> None:
        if self._subscription is not None:
            self.qos = self._subscription.qos  # a step down to best effort stays
            self._subscription.close()
            self._subscription = self.subscribed_type = None
        self.subscribed_type = pose_type
        self._subscription = self.node.subscribe_input(
            pose_message_class(pose_type), self.topic, self.callback, self.qos
        )

    def discover(self) -> None:
        """One look at the topic's publishers: confirm or switch the type, warn once on conflicts."""
        infos = self.node.get_publishers_info_by_topic(self.resolved_topic)
        types = sorted({str(i.topic_type) for i in infos})
        supported = [t for t in types if pose_type_of(t)]
        unsupported = [t for t in types if not pose_type_of(t)]
        if unsupported and 'unsupported' not in self._warned:
            self._warned.add('unsupported')
            self.node.get_logger().warning(
                f'{self.resolved_topic} is published as {", ".join(unsupported)}: not a pose type this node '
                f'reads ({", ".join(POSE_MESSAGE_TYPES.values())})'
            )
        if len(supported) > 1 and 'conflict' not in self._warned:
            self._warned.add('conflict')
            who = ', '.join(f'{i.node_name} ({i.topic_type})' for i in infos)
            self.node.get_logger().warning(
                f'{self.resolved_topic} has publishers of several pose types: {who}; subscribed with '
                f'{self.pose_type or supported[0]} only. Set pose_type, or remap one of the sources'
            )
        if self.pose_type is None and supported:
            found = pose_type_of(supported[0]) or self.PROVISIONAL
            # Decided before subscribing: a publisher that matches the new subscription (on
            # another thread, at once) must already find the type it was matched for.
            self.pose_type = found
            if found != self.subscribed_type:
                self._subscribe(found)
            self.node.get_logger().info(f'pose_type auto: {self.resolved_topic} is {supported[0]}')
            self.node.destroy_timer(self._timer)
            self._timer = self.node.create_wall_timer(self.SLOW_PERIOD, self.discover)
