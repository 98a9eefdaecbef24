"""What the nodes tell the rest of the graph about themselves: "ready", and each keyframe's fate.

Two small topics, so that a replayer and a runner can follow the graph's progress over DDS in
any deployment (one process or several) without reading logs or introspecting the ROS graph:

* ``depth_fusion/ready`` (``std_msgs/String``, reliable, transient-local): each node publishes
  one JSON line once it can process inputs (warm-up done, subscriptions made), naming itself
  and the topics it subscribes to. Transient-local: a replayer or runner started later still
  hears every node that is ready (each writer keeps its own last sample).
* ``depth_fusion/keyframe/events`` (``std_msgs/Header``, reliable, deep history): one message
  per event, ``stamp`` = the stamp of the image or keyframe concerned, ``frame_id`` = the
  event: ``image`` (multi_view_node has handled an input image: posed, buffered or dropped),
  ``image_waiting`` (it has the image, which waits for its pose; ``image`` follows),
  ``image_done`` (multi_view_node is done with it: its filter has updated with it, or it was
  never for the filter), ``chosen`` (the keyframe policy chose it), ``fused`` (fusion_node
  published its fused depth)
  or ``dropped:<node>.<reason>`` (a node gave the keyframe up, e.g.
  ``dropped:multi_view.worker_queue_full``).
  One writer per node keeps each node's events in order: a replayer that sees ``image`` for a
  stamp has already seen ``chosen`` for it when it was chosen.

:class:`KeyframeLedger` turns the events into counts (chosen, fused, dropped by reason, in
flight): the back-pressure of a paced replay and the honest summary of a run.
"""

from __future__ import annotations

import bisect
import json
import threading
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

TOPIC_READY = 'depth_fusion/ready'
TOPIC_KEYFRAME_EVENTS = 'depth_fusion/keyframe/events'

EVENT_IMAGE = 'image'
EVENT_IMAGE_WAITING = 'image_waiting'
EVENT_IMAGE_DONE = 'image_done'
EVENT_CHOSEN = 'chosen'
EVENT_FUSED = 'fused'
DROPPED = 'dropped:'

#: Deep enough that a burst of events (a replay catching up) is never overwritten before it is
#: read; each event is a few dozen bytes.
EVENTS_DEPTH = 1000
#: ``image`` stamps a ledger keeps (:meth:`KeyframeLedger.image_ns`).
RECENT_IMAGES = 8
#: History of a ready-line reader: more than the nodes of any graph.
READERS_DEPTH = 100


def events_qos() -> QoSProfile:
    """Reliable, volatile, deep history: every event reaches a matched reader."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=EVENTS_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def ready_qos(depth: int = 1) -> QoSProfile:
    """Reliable, transient-local: a late reader hears every node that is ready.

    A writer keeps its one line (depth 1); a reader keeps many (``READERS_DEPTH``): the lines of
    all the nodes arrive at once when it joins, and with depth 1 it would keep only the last.
    """
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


@dataclass(frozen=True)
class ReadyStatus:
    """One node's ready line: its name, the topics it subscribes to, seconds its start took,
    and whether it is *warm*: at full speed (false while kernels compile in the background: it
    processes inputs already, slower; a second line says warm when they are built)."""

    node: str
    subscribes: tuple[str, ...]
    seconds: float
    warm: bool = True

    def to_json(self) -> str:
        doc = {'node': self.node, 'subscribes': list(self.subscribes), 'seconds': self.seconds}
        return json.dumps({**doc, 'warm': self.warm})

    @classmethod
    def from_json(cls, text: str) -> ReadyStatus:
        """Parse a ready line; ``ValueError`` when it is not one (no ``warm``: warm)."""
        try:
            doc = json.loads(text)
            subscribes = tuple(str(t) for t in doc['subscribes'])
            return cls(str(doc['node']), subscribes, float(doc['seconds']), bool(doc.get('warm', True)))
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f'not a ready status: {text[:80]!r} ({exc})') from None


class GraphEvents:
    """A node's side: publish its ready line once, and its keyframe events.

    Created early in the node's constructor (so the readers match while it warms up);
    :meth:`ready` is called last, after the subscriptions exist.
    """

    def __init__(self, node: Any) -> None:
        from std_msgs.msg import Header, String

        self._node = node
        self._header_cls = Header
        self._string_cls = String
        self._events = node.create_publisher(Header, TOPIC_KEYFRAME_EVENTS, events_qos())
        self._ready = node.create_publisher(String, TOPIC_READY, ready_qos())
        self._lock = threading.Lock()
        self.started = time.monotonic()
        self._subscribes: tuple[str, ...] | None = None  # set by ready()
        self._warm_early = False
        self._closed = False

    def close(self) -> None:
        """Publish nothing from now on: the node is going. A thread of its own that outlives
        the node's publishers (the fusion node's background compilation says ``warm``) would
        otherwise raise in rclpy (``InvalidHandle``) as it ends."""
        with self._lock:
            self._closed = True

    def event(self, stamp_ns: int, event: str) -> None:
        """Publish one event about the image / keyframe stamped ``stamp_ns``."""
        msg = self._header_cls()
        msg.stamp.sec, msg.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        msg.frame_id = event
        with self._lock:  # callbacks and the worker both publish; keep their order
            if not self._closed:
                self._events.publish(msg)

    def dropped(self, stamp_ns: int, reason: str) -> None:
        """``dropped:multi_view.worker_queue_full``: which node gave the keyframe up, and why."""
        self.event(stamp_ns, f'{DROPPED}{self._node.get_name().removesuffix("_node")}.{reason}')

    def ready(self, subscribes: Iterable[str] | None = None, warm: bool = True) -> ReadyStatus:
        """Tell the graph this node processes inputs from now on; logs the one "ready" line.
        ``warm=False``: still warming up in the background; :meth:`warm` follows (any thread)."""
        node = self._node
        if subscribes is None:
            subscribes = sorted({s.topic_name for s in node.subscriptions})
        with self._lock:
            self._subscribes = tuple(subscribes)
            status = self._publish_status(warm or self._warm_early)
        warming = '' if status.warm else ', warming up'
        node.get_logger().info(f'ready ({status.seconds:.1f} s after start{warming})')
        return status

    def warm(self, what: str = 'warm') -> ReadyStatus | None:
        """Tell the graph the background warm-up is over: the ready line again, ``warm``. Before
        :meth:`ready` it only makes the ready line say warm."""
        with self._lock:
            if self._closed:
                return None
            if self._subscribes is None:
                self._warm_early = True
                return None
            status = self._publish_status(True)
        self._node.get_logger().info(f'{what} ({status.seconds:.1f} s after start)')
        return status

    def _publish_status(self, warm: bool) -> ReadyStatus:
        """Publish this node's ready line (lock held, after :meth:`ready` set the subscriptions)."""
        seconds = time.monotonic() - self.started
        status = ReadyStatus(self._node.get_fully_qualified_name(), self._subscribes, seconds, warm)
        self._ready.publish(self._string_cls(data=status.to_json()))
        return status


def header_stamp(msg: Any) -> int:
    return int(msg.stamp.sec) * 1_000_000_000 + int(msg.stamp.nanosec)


@dataclass
class LedgerSnapshot:
    """Counts at one instant (stamps kept so a runner can name what is missing)."""

    images: int = 0
    chosen: list[int] = field(default_factory=list)
    fused: list[int] = field(default_factory=list)
    dropped: dict[int, str] = field(default_factory=dict)

    @property
    def in_flight(self) -> list[int]:
        """Chosen keyframes with no final event yet (being processed, or lost on the way)."""
        done = set(self.fused) | set(self.dropped)
        return [s for s in self.chosen if s not in done]

    def drop_reasons(self) -> dict[str, int]:
        return dict(Counter(self.dropped[s] for s in self.chosen if s in self.dropped))


class KeyframeLedger:
    """Chosen / fused / dropped keyframes and handled images, from the events (thread-safe).

    A keyframe's first final event wins (a stray second one, e.g. a late part dropped after
    fusion, does not change it).
    """

    def __init__(self) -> None:
        self._lock = threading.Condition()
        self._images = 0
        self._last_done_ns = -1
        self._last_seen_ns = -1
        #: The newest ``image`` stamps, in order (:meth:`image_ns`).
        self._recent_images: list[int] = []
        self._chosen: dict[int, None] = {}
        self._final: dict[int, str] = {}
        self.last_event = time.monotonic()

    def on_event(self, msg: Any) -> None:
        """Subscription callback of :data:`TOPIC_KEYFRAME_EVENTS`."""
        self.add(header_stamp(msg), str(msg.frame_id))

    def add(self, stamp_ns: int, event: str) -> None:
        with self._lock:
            self.last_event = time.monotonic()
            if event == EVENT_IMAGE:
                self._images += 1
                self._last_seen_ns = max(self._last_seen_ns, stamp_ns)
                bisect.insort(self._recent_images, stamp_ns)
                del self._recent_images[:-RECENT_IMAGES]
            elif event == EVENT_IMAGE_WAITING:
                self._last_seen_ns = max(self._last_seen_ns, stamp_ns)
            elif event == EVENT_IMAGE_DONE:
                self._last_done_ns = max(self._last_done_ns, stamp_ns)
            elif event == EVENT_CHOSEN:
                self._chosen.setdefault(stamp_ns, None)
            elif event == EVENT_FUSED or event.startswith(DROPPED):
                self._final.setdefault(stamp_ns, event.removeprefix(DROPPED))
            self._lock.notify_all()

    def image_ns(self, back: int = 1) -> int:
        """Stamp of the ``back``-th newest image handled (1: the newest; -1: fewer than that,
        or ``back`` beyond :data:`RECENT_IMAGES`)."""
        with self._lock:
            recent = self._recent_images
            return recent[-back] if 1 <= back <= len(recent) else -1

    @property
    def last_seen_ns(self) -> int:
        """Stamp of the newest image multi_view_node has (handled, or waiting for its pose; -1: none)."""
        with self._lock:
            return self._last_seen_ns

    @property
    def last_done_ns(self) -> int:
        """Stamp of the newest image multi_view_node is done with (-1: none)."""
        with self._lock:
            return self._last_done_ns

    def in_flight(self) -> int:
        with self._lock:
            return sum(1 for s in self._chosen if s not in self._final)

    def wait(self, timeout: float) -> None:
        """Sleep until the next event or ``timeout`` s."""
        with self._lock:
            self._lock.wait(timeout)

    def snapshot(self) -> LedgerSnapshot:
        with self._lock:
            fused = [s for s, e in self._final.items() if e == EVENT_FUSED]
            dropped = {s: e for s, e in self._final.items() if e != EVENT_FUSED}
            return LedgerSnapshot(self._images, sorted(self._chosen), sorted(fused), dropped)


class ReadyWatcher:
    """Collects the ready lines of the graph's nodes (subscription callback + queries)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.statuses: dict[str, ReadyStatus] = {}
        self.arrival: dict[str, float] = {}
        #: Each node's first warm status (its ready line when it was warm at once).
        self.warm_statuses: dict[str, ReadyStatus] = {}
        self.errors: list[str] = []

    def on_ready(self, msg: Any) -> None:
        try:
            status = ReadyStatus.from_json(msg.data)
        except ValueError as exc:
            with self._lock:
                self.errors.append(str(exc))
            return
        with self._lock:
            self.statuses.setdefault(status.node, status)  # the ready line (a warm line repeats it)
            self.arrival.setdefault(status.node, time.monotonic())
            if status.warm:
                self.warm_statuses.setdefault(status.node, status)

    def missing(self, nodes: Sequence[str]) -> list[str]:
        """Of ``nodes`` (names, with or without the leading '/'), those not ready yet."""
        with self._lock:
            have = set(self.statuses)
        return [n for n in nodes if _full_name(n) not in have]

    def cold(self, nodes: Sequence[str]) -> list[str]:
        """Of ``nodes``, those that are ready but have not said they are warm yet."""
        with self._lock:
            ready = [n for n in nodes if _full_name(n) in self.statuses]
            return [n for n in ready if _full_name(n) not in self.warm_statuses]

    def subscribers_of(self, topic: str, nodes: Sequence[str]) -> int:
        """How many of the ready ``nodes`` subscribe to ``topic``."""
        with self._lock:
            found = [self.statuses.get(_full_name(n)) for n in nodes]
        return sum(1 for s in found if s is not None and topic in s.subscribes)


def _full_name(node: str) -> str:
    return node if node.startswith('/') else '/' + node


def subscribe_events(
    node: Any, ledger: KeyframeLedger, watcher: ReadyWatcher | None = None, **kwargs: Any
) -> list[Any]:
    """Subscribe ``node`` to the events (and the ready lines) on behalf of a ledger / watcher."""
    from std_msgs.msg import Header, String

    subs = [node.create_subscription(Header, TOPIC_KEYFRAME_EVENTS, ledger.on_event, events_qos(), **kwargs)]
    if watcher is not None:
        qos = ready_qos(READERS_DEPTH)
        subs.append(node.create_subscription(String, TOPIC_READY, watcher.on_ready, qos, **kwargs))
    return subs
