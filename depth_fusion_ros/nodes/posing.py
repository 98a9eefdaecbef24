"""How multi_view_node poses its images, told to the nodes after it (map_node).

multi_view_node reads each image's camera pose as ``T_pose(stamp + offset) @ T_pose_cam``:
the pose source's pose at the image stamp plus ``offset`` (``pose_time_offset`` and the time
offset check's correction), then ``T_pose_cam`` (``camera_from_pose_frame`` and the mount
check's turn). Its checks change both while it runs. A node that compares the keyframes'
camera poses with the pose source's own poses later (map_node, with a corrected trajectory
from a loop closure) must undo exactly that posing, keyframe by keyframe: with the
configured ``camera_from_pose_frame`` alone it read a mount turn as a move of every keyframe,
rebuilt the map and lost the turn. So multi_view_node publishes its posing, latched, with
its first posed frame and at every restart of its frame history: each change of the posing
causes one, as a restarted stream or a pose jump does (the same posing again changes nothing).
The topics keep the last posings (:func:`posing_qos`), so a node that joins later hears the
posings before the current one too:

* ``depth_fusion/posing/camera_from_pose_frame`` (geometry_msgs/TransformStamped): the camera
  (``child_frame_id``: the images' frame) in the pose source's frame (``header.frame_id``
  ``pose_frame``: PoseStamped names no child frame), as TF would hold it (there is no TF on
  pip: docs/nodes.md);
* ``depth_fusion/posing/pose_time`` (sensor_msgs/TimeReference): ``time_ref`` is the pose
  source's time an image stamped ``header.stamp`` is posed at (``source``: where the offset
  comes from).

Both are stamped with the first image posed that way, so a keyframe still in flight when
the posing changed is matched with the posing it was posed with (:class:`PosingLog`).

A time offset correction is also applied backwards, by the node that still has the pose
source's poses around the keyframes posed before it: multi_view_node reads them again at the
corrected offset and publishes them with the new posing:

* ``depth_fusion/posing/reposed_keyframes`` (nav_msgs/Path): the camera poses of the
  keyframes posed at the old offset, read again at the new one (``header.stamp``: the first
  image of the new posing, as on ``pose_time``; each pose stamped with its keyframe). map_node
  moves those keyframes there (kept, waiting, or still in flight) and rebuilds the map.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import TimeReference

from ..data import messages
from ..pose_corrections import Posing
from .qos import latched_qos

TOPIC_POSING_TRANSFORM = 'depth_fusion/posing/camera_from_pose_frame'
TOPIC_POSING_TIME = 'depth_fusion/posing/pose_time'
TOPIC_REPOSED_KEYFRAMES = 'depth_fusion/posing/reposed_keyframes'
#: ``header.frame_id`` of the transform: the frame of the pose topic's poses.
POSE_FRAME = 'pose_frame'
#: Posings a log keeps (a handful change per run; the oldest go first), and the posing messages
#: the topics keep for a node that joins later (:func:`posing_qos`).
LOG_SIZE = 32
#: Poses re-read at a corrected time offset that a node keeps for keyframes still in flight (a
#: few per correction; bounded against a keyframe that never comes).
IN_FLIGHT = 256


#: ``reread(stamps_s, before, after)``: the camera poses of frames posed at ``stamp + before``,
#: read again at ``stamp + after`` (None where the pose source's poses are gone).
Reread = Callable[[list[float], float, float], list[np.ndarray | None]]


def posing_qos() -> Any:
    """Latched with the last :data:`LOG_SIZE` posings, not the last one only: a map_node started
    after a mount turn still hears the posing before it, so a keyframe posed before the turn and
    still in flight is re-posed in the turn (:meth:`PosingLog.in_latest`) instead of being taken
    as posed in it."""
    return latched_qos(LOG_SIZE)


def transform_msg(posing: Posing, stamp_ns: int, camera_frame: str, *, kind: Any) -> Any:
    """The ``camera_from_pose_frame`` message of ``posing``, stamped ``stamp_ns``."""
    k = messages.as_kind(kind)
    pose = messages.pose_msg(posing.T_pose_cam, kind=k)
    p = pose.position
    translation = k.new('geometry_msgs/msg/Vector3', x=p.x, y=p.y, z=p.z)
    transform = k.new('geometry_msgs/msg/Transform', translation=translation, rotation=pose.orientation)
    return k.new(
        'geometry_msgs/msg/TransformStamped',
        header=messages.header_msg(int(stamp_ns), POSE_FRAME, kind=k),
        child_frame_id=camera_frame,
        transform=transform,
    )


def time_reference_msg(posing: Posing, stamp_ns: int, source: str, *, kind: Any) -> Any:
    """The ``pose_time`` message of ``posing``: image ``stamp_ns`` is posed at ``time_ref``."""
    k = messages.as_kind(kind)
    return k.new(
        'sensor_msgs/msg/TimeReference',
        header=messages.header_msg(int(stamp_ns), '', kind=k),
        time_ref=messages.time_msg(int(stamp_ns) + messages.sec_to_ns(posing.offset), kind=k),
        source=source,
    )


class PosingPublisher:
    """multi_view_node's side: publishes its posing from a frame on. The node calls it with the
    first frame it poses and at each restart of its frame history, which every change of its
    posing causes (a time offset or mount correction), as a restarted stream does (its
    keyframes are then matched from its own first stamp).

    It keeps the stamps of the last ``keep`` keyframes (:meth:`keyframe`): when the time offset
    changed, those posed at the old one are read again at the new one (``reread``: the node's
    pose buffer) and published on :data:`TOPIC_REPOSED_KEYFRAMES`."""

    def __init__(self, node: Any, source: str, keep: int) -> None:
        self._transform_pub = node.create_publisher(TransformStamped, TOPIC_POSING_TRANSFORM, posing_qos())
        self._time_pub = node.create_publisher(TimeReference, TOPIC_POSING_TIME, posing_qos())
        self._reposed_pub = node.create_publisher(PathMsg, TOPIC_REPOSED_KEYFRAMES, posing_qos())
        self._source = source
        self._keyframes: deque[int] = deque(maxlen=keep)
        self._offset: float | None = None  # of the posing published last
        self.published = 0

    def keyframe(self, stamp_ns: int) -> None:
        """A keyframe was chosen (its pose is published with it)."""
        self._keyframes.append(int(stamp_ns))

    def forget_keyframes(self) -> None:
        """A new stream: the pose source's poses of the keyframes before are gone."""
        self._keyframes.clear()

    def publish(
        self, stamp_ns: int, camera_frame: str, posing: Posing, reread: Reread, world_frame: str
    ) -> tuple[int, int] | None:
        """The frames from the one stamped ``stamp_ns`` on are posed with ``posing``. When its
        time offset is another than the last posing's, the keyframes before are read again at it
        and published: returns ``(re-read, keyframes before)``, else None."""
        kind = messages.RCLPY
        self._transform_pub.publish(transform_msg(posing, stamp_ns, camera_frame, kind=kind))
        self._time_pub.publish(time_reference_msg(posing, stamp_ns, self._source, kind=kind))
        self.published += 1
        before, self._offset = self._offset, posing.offset
        if before is None or before == posing.offset:
            return None
        stamps = [s for s in self._keyframes if s < stamp_ns]
        poses = reread([messages.ns_to_sec(s) for s in stamps], before, posing.offset)
        found = [(s, T) for s, T in zip(stamps, poses, strict=True) if T is not None]
        if found:
            self._reposed_pub.publish(reposed_msg(stamp_ns, world_frame, found, kind=kind))
        return len(found), len(stamps)


def reposed_msg(stamp_ns: int, world_frame: str, poses: list[tuple[int, np.ndarray]], *, kind: Any) -> Any:
    """The ``reposed_keyframes`` message: keyframes ``(stamp_ns, T_wc)`` posed before the posing
    that begins at ``stamp_ns``, read again in it."""
    k = messages.as_kind(kind)
    return k.new(
        'nav_msgs/msg/Path',
        header=messages.header_msg(int(stamp_ns), world_frame, kind=k),
        poses=[
            messages.pose_stamped_msg(T, messages.header_msg(int(s), world_frame, kind=k), kind=k)
            for s, T in poses
        ],
    )


@dataclass
class PosingLog:
    """The nodes after multi_view_node (map_node, the adaptation): the posings heard, each from
    the first stamp it applies to, and the re-read poses of keyframes still in flight.

    :meth:`at` gives a keyframe's posing by its stamp: the newest one that began at or before
    it, else the oldest one heard (a keyframe from before the first, or a restarted stream's
    first). A posing that begins before the newest one heard (the stream restarted) starts
    the log over. None until multi_view_node said anything: the node's own default then."""

    transforms: list[tuple[int, np.ndarray]] = field(default_factory=list)
    offsets: list[tuple[int, float]] = field(default_factory=list)
    #: Poses multi_view_node re-read at a corrected time offset for keyframes whose own pose
    #: has not come yet, by stamp (ns), in the newest transform (:meth:`hold`, :meth:`arriving`).
    in_flight: dict[int, np.ndarray] = field(default_factory=dict)

    def on_transform(self, msg: Any) -> np.ndarray | None:
        """A ``camera_from_pose_frame`` message (raises ``ValueError`` for a non-rigid one).
        Returns the turn ``before^-1 @ after`` when the newest transform changed (a mount check
        turned the camera: what was posed before is re-posed by it, the poses held in flight
        here too), else None."""
        before = self.latest
        T = messages.transform_to_matrix(msg.transform)
        _add(self.transforms, messages.stamp_to_ns(msg.header.stamp), T)
        if before is None or _same(before, T):
            return None
        turn = np.linalg.inv(before) @ T
        self.in_flight = {stamp: pose @ turn for stamp, pose in self.in_flight.items()}
        return turn

    def on_time(self, msg: Any) -> None:
        """A ``pose_time`` message."""
        stamp = messages.stamp_to_ns(msg.header.stamp)
        offset = messages.ns_to_sec(messages.stamp_to_ns(msg.time_ref) - stamp)
        _add(self.offsets, stamp, offset)

    def offset_from(self, stamp_ns: int) -> float | None:
        """The time offset of the posing said to begin at ``stamp_ns`` exactly (None: not heard)."""
        return next((offset for begins, offset in self.offsets if begins == stamp_ns), None)

    def retime(self, first_ns: int, until_ns: int, offset: float) -> None:
        """The images from ``first_ns`` to before ``until_ns`` were posed again at ``offset``
        (multi_view_node re-read them at a corrected time offset)."""
        before = [e for e in self.offsets if e[0] < first_ns]
        self.offsets = [*before, (first_ns, offset), *(e for e in self.offsets if e[0] >= until_ns)]

    def reread_in_latest(
        self, begins_ns: int, stamps_ns: np.ndarray, poses: np.ndarray
    ) -> dict[int, np.ndarray]:
        """A ``reposed_keyframes`` message's poses (read in the posing that begins at
        ``begins_ns``) in the newest transform, by stamp (ns): a turn heard since applies."""
        begins = messages.ns_to_sec(begins_ns)
        return {int(s): self.in_latest(begins, T) for s, T in zip(stamps_ns.tolist(), poses, strict=True)}

    def hold(self, poses: dict[int, np.ndarray]) -> None:
        """Keep re-read poses (by stamp, ns) of keyframes whose own pose has not come yet; the
        oldest go beyond :data:`IN_FLIGHT` (a keyframe that never comes)."""
        self.in_flight.update(poses)
        for stamp in list(self.in_flight)[:-IN_FLIGHT]:
            del self.in_flight[stamp]

    def arriving(self, stamp_ns: int, T_wc: np.ndarray) -> np.ndarray:
        """The pose a keyframe's own pose message stands for when it comes: the one re-read at a
        corrected time offset while it was in flight, else its own in the newest transform
        (:meth:`in_latest`)."""
        reread = self.in_flight.pop(int(stamp_ns), None)
        return reread if reread is not None else self.in_latest(messages.ns_to_sec(stamp_ns), T_wc)

    def at(self, stamp_s: float) -> Posing | None:
        """The posing the image stamped ``stamp_s`` was posed with."""
        if not self.transforms and not self.offsets:
            return None
        stamp_ns = messages.sec_to_ns(stamp_s)
        T = _lookup(self.transforms, stamp_ns, None)
        return Posing(np.eye(4) if T is None else T, float(_lookup(self.offsets, stamp_ns, 0.0)))

    def in_latest(self, stamp_s: float, T_wc: np.ndarray) -> np.ndarray:
        """A camera pose of the image stamped ``stamp_s`` in the newest transform: one posed
        before a turn and arriving after it (in flight meanwhile) is re-posed as the ones kept
        were, ``T_wc @ then^-1 @ now``."""
        then, now = self.at(stamp_s), self.latest
        if then is None or now is None or _same(then.T_pose_cam, now):
            return T_wc
        return T_wc @ np.linalg.inv(then.T_pose_cam) @ now

    def current(self, stamp_s: float) -> Posing | None:
        """The posing a keyframe stamped ``stamp_s`` is kept in: the newest transform (the map
        node re-poses what came before a mount turn, ``MapPosing.on_transform``) with the time
        offset it was posed at, or re-read at (:meth:`retime`)."""
        posing = self.at(stamp_s)
        if posing is None or not self.transforms:
            return posing
        return Posing(self.transforms[-1][1], posing.offset)

    @property
    def latest(self) -> np.ndarray | None:
        """The newest ``camera_from_pose_frame`` heard (None: none yet)."""
        return self.transforms[-1][1] if self.transforms else None


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """The same transform (to rounding: one sent twice, or through a message)."""
    return bool(np.allclose(a, b, rtol=0.0, atol=1e-9))


def _add(log: list, stamp_ns: int, value: Any) -> None:
    if log and stamp_ns < log[-1][0]:
        log.clear()  # a restarted stream: what came before is another stream's
    log.append((stamp_ns, value))
    del log[:-LOG_SIZE]


def _lookup(log: list, stamp_ns: int, default: Any) -> Any:
    for begins, value in reversed(log):
        if begins <= stamp_ns:
            return value
    return log[0][1] if log else default
