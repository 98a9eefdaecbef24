"""``bag_replayer``: plays a rosbag2 (mcap or sqlite3) onto ROS topics, like ``ros2 bag play``.

Why our own player: ``rosbag2_py`` and ``ros2 bag`` do not exist for a pip-installed ROS 2
(see ROS2_PIP.md), while ``rosbags`` reads both storages and rclpy publishes serialized CDR
bytes as they are. So the replayer never deserializes a message: the bag's bytes go straight
to the wire, which keeps a 640x480 stream cheap on a small CPU.

Playback runs in its own thread that sleeps until each message is due (the GIL is free while
it sleeps), so in a composed process the executor keeps serving the processing nodes.

Looping replays the bag again with every header stamp (and ``/clock``) shifted forward by the
bag's length, patched in the CDR bytes: downstream pose buffers and time sources then see time
moving forward, which is what a long soak test needs.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock as SteadyClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# re-exported: BagError, has_leading_header, header_stamp_ns, shift_header_stamp and calibration_first
# (test/test_replayer.py and test/run_bags.py import them from this module).
from ..data.bag_open import BagError, open_bag
from ..data.bag_qos import recorded_latched_depth
from ..data.cdr_stamps import has_leading_header, header_stamp_ns, shift_header_stamp
from ..data.instant_order import calibration_first
from .diagnostics import TOPIC_DIAGNOSTICS, replayer_array
from .pacer import Pacer
from .params import ParamSpec, declare_parameters
from .qos import latched_qos

NODE_NAME = 'bag_replayer'  # data.bag_open prefixes its errors with the same name

#: Every parameter of the node (``config/depth_fusion.yaml`` section ``bag_replayer``).
REPLAYER_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec('bag', '', 'rosbag2 to play: its folder (with metadata.yaml), or one .mcap / .db3 file'),
    ParamSpec('rate', 1.0, 'playback speed as a multiple of the recorded rate', 0.01, 100.0),
    ParamSpec('start_offset', 0.0, 'seconds of the bag skipped at the start', 0.0, None),
    ParamSpec('loop', False, 'play the bag again when it ends (header stamps shifted forward each pass)'),
    ParamSpec(
        'loop_seconds',
        0.0,
        'with loop: stop after this many seconds of wall time (0: loop until shut down)',
        0.0,
        None,
    ),
    ParamSpec('topics', [''], "topics of the bag to play (empty or ['']: all)"),
    ParamSpec('remap', [''], "topic remapping as 'from:=to' strings, applied before ROS -r rules"),
    ParamSpec('publish_clock', False, 'publish the bag time on /clock (for use_sim_time nodes)'),
    ParamSpec('clock_frequency', 100.0, 'how often /clock is published between messages, Hz', 1.0, 1000.0),
    ParamSpec('reliable', True, 'reliable QoS (matches every subscriber); false: best effort'),
    ParamSpec('qos_depth', 10, 'history depth of each publisher', 1, 10000),
    ParamSpec(
        'wait_for_subscribers',
        0,
        'before playing, wait until each topic of wait_topics has at least this many subscribers',
        0,
        1000,
    ),
    ParamSpec('wait_topics', [''], "topics wait_for_subscribers applies to (empty or ['']: all played)"),
    ParamSpec(
        'wait_for_nodes',
        [''],
        'before playing, wait until these nodes exist and their subscriptions to played topics match',
    ),
    ParamSpec(
        'wait_timeout',
        60.0,
        'give up waiting after this many seconds and play anyway (0: forever)',
        0.0,
        None,
    ),
    ParamSpec(
        'start_delay',
        0.0,
        'seconds to wait after the subscribers are there, before the first message (lets the rest '
        'of the graph finish discovery)',
        0.0,
        600.0,
    ),
    ParamSpec(
        'wait_ready',
        [''],
        'before playing, wait until these nodes said they are ready (on depth_fusion/ready) and this '
        "replayer's publishers are matched with their subscriptions (empty or ['']: do not wait)",
    ),
    ParamSpec(
        'wait_warm',
        0.0,
        'then wait up to this many seconds for the wait_ready nodes that warm up in the background '
        '(fusion_node compiling its kernels) to say they are warm, so the replay meets the graph at '
        'full speed; then play anyway, with a warning (0: play as soon as they are ready)',
        0.0,
        600.0,
    ),
    ParamSpec(
        'pace',
        False,
        'paced replay: before each image of pace_topic, wait while the graph is busy (see '
        'max_keyframes_in_flight); never faster than rate. Lossless on a slow machine; false: play at '
        'the recorded rate whatever the graph does (real time)',
    ),
    ParamSpec('pace_topic', '/camera/rgb/image_color', 'pace: the camera image topic (as published)'),
    ParamSpec(
        'max_keyframes_in_flight',
        1,
        'pace: chosen keyframes not yet fused (nor dropped) at most before the next image waits. 1: '
        'the next keyframe is sent when the graph is done, so a paced replay shows the latency of a '
        'graph that keeps up; 2 pipelines two keyframes (10-20 % more keyframes/s, 40 % more latency)',
        1,
        1000,
    ),
    ParamSpec(
        'max_images_ahead',
        4,
        'pace: images sent that have not reached multi_view_node yet, at most (one that waits there for '
        'its pose has reached it, so a pose stream that lags the images never stalls the replay)',
        1,
        1000,
    ),
    ParamSpec(
        'pace_timeout',
        120.0,
        'pace: without any progress from the graph for this many seconds, pacing is switched off '
        '(warning) and the replay goes on at the recorded rate',
        0.1,
        None,
    ),
    ParamSpec('linger', 0.5, 'seconds to stay up after the last message so it is delivered', 0.0, 60.0),
)


def parse_remaps(items: Sequence[str]) -> dict[str, str]:
    """``['/a:=/b']`` -> ``{'/a': '/b'}``; empty strings are ignored (ROS has no empty arrays)."""
    remaps: dict[str, str] = {}
    for item in items:
        if not item:
            continue
        src, sep, dst = item.partition(':=')
        if not sep or not src.strip() or not dst.strip():
            raise ValueError(f"{NODE_NAME}: parameter 'remap': expected 'from:=to', got {item!r}")
        remaps[src.strip()] = dst.strip()
    return remaps


def non_empty(items: Sequence[str]) -> list[str]:
    return [s for s in items if s]


def ros_message_class(msgtype: str) -> type:
    """rclpy message class of a rosbags type name such as ``sensor_msgs/msg/Image``."""
    package, _, name = msgtype.rpartition('/')
    module = importlib.import_module(package.replace('/', '.'))
    return getattr(module, name)


@dataclass
class PlayedTopic:
    """One bag topic as played: where it goes and whether its stamp can be patched."""

    bag_topic: str
    out_topic: str
    msgtype: str
    stampable: bool
    publisher: Any = None
    connections: list[Any] = field(default_factory=list)


@dataclass
class PlaybackStats:
    """What was played, for logs, tests and the benchmark."""

    published: Counter = field(default_factory=Counter)
    passes: int = 0
    started_wall: float | None = None
    ended_wall: float | None = None
    #: Largest delay of a publish behind its due time (s): how far playback fell behind.
    max_lag: float = 0.0


# --- the node -----------------------------------------------------------------------------------


class BagReplayer(Node):
    """Publishes a rosbag2's messages at the recorded rate times ``rate``.

    ``finished`` is set when playback ended (end of bag, ``loop_seconds`` reached or stopped);
    ``on_finished`` (optional) is called from the playback thread at that moment. With
    ``autostart=False`` playback begins only when :meth:`start` is called, so a launcher can
    create every node of a composed graph first.
    """

    def __init__(
        self,
        *,
        autostart: bool = True,
        on_finished: Callable[[], None] | None = None,
        node_name: str = NODE_NAME,
        **kwargs: Any,
    ) -> None:
        super().__init__(node_name, **kwargs)
        self.params = declare_parameters(self, REPLAYER_PARAMS)
        self.finished = threading.Event()
        self.stats = PlaybackStats()
        self.error: BaseException | None = None
        self._on_finished = on_finished
        self._stop = threading.Event()
        self._reader = open_bag(self.params['bag'])
        try:
            self._topics = self._plan_topics()
            self._play_start_ns, self._loop_period_ns = self._plan_times()
        except BaseException:
            self._reader.close()
            raise
        self._clock_pub = None
        if self.params['publish_clock']:
            from rosgraph_msgs.msg import Clock

            clock_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
            self._clock_pub = self.create_publisher(Clock, '/clock', clock_qos)
            self._clock_msg = Clock()
        self.pacer: Pacer | None = None
        if self.params['pace'] or non_empty(self.params['wait_ready']):
            self.pacer = Pacer(
                self,
                max_keyframes=self.params['max_keyframes_in_flight'],
                max_images_ahead=self.params['max_images_ahead'],
                timeout=self.params['pace_timeout'],
                stop=self._stop,
                warn=self.get_logger().warning,
                enabled=bool(self.params['pace']),
            )
        self._thread = threading.Thread(target=self._run, name='bag_replayer', daemon=True)
        self._diagnostics_pub = self.create_publisher(
            DiagnosticArray, TOPIC_DIAGNOSTICS, QoSProfile(depth=10)
        )
        self.create_timer(1.0, self.publish_diagnostics, clock=SteadyClock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'playing {self._reader.path} ({len(self._topics)} topics, '
            f'{self._reader.message_count} messages, {self._reader.duration / 1e9:.1f} s) '
            f'at rate {self.params["rate"]:g}'
            + (' in a loop' if self.params['loop'] else '')
            + (', paced by the graph' if self.params['pace'] else '')
        )
        if autostart:
            self.start()

    # -- set-up --

    def _plan_topics(self) -> dict[str, PlayedTopic]:
        wanted = set(non_empty(self.params['topics']))
        remaps = parse_remaps(self.params['remap'])
        in_bag = {c.topic for c in self._reader.connections}
        unknown = sorted(wanted - in_bag)
        if unknown:
            raise BagError(
                f'{NODE_NAME}: topics {unknown} are not in {self._reader.path} (it has {sorted(in_bag)})'
            )
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.params['qos_depth'],
            reliability=ReliabilityPolicy.RELIABLE
            if self.params['reliable']
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.VOLATILE,
        )
        topics: dict[str, PlayedTopic] = {}
        latched: list[str] = []
        for conn in self._reader.connections:
            if wanted and conn.topic not in wanted:
                continue
            if conn.topic in topics:
                topics[conn.topic].connections.append(conn)
                continue
            try:
                msg_cls = ros_message_class(conn.msgtype)
            except (ImportError, AttributeError, ValueError):
                self.get_logger().warning(
                    f'skipping {conn.topic}: message type {conn.msgtype} is not installed'
                )
                continue
            played = PlayedTopic(
                conn.topic, remaps.get(conn.topic, conn.topic), conn.msgtype, has_leading_header(conn.msgtype)
            )
            kept = recorded_latched_depth(conn)
            if kept:  # offered transient local when recorded: a late subscriber still hears it
                latched.append(played.out_topic)
            topic_qos = latched_qos(max(kept, self.params['qos_depth'])) if kept else qos
            played.publisher = self.create_publisher(msg_cls, played.out_topic, topic_qos)
            played.connections.append(conn)
            topics[conn.topic] = played
        if not topics:
            raise BagError(f'{NODE_NAME}: nothing to play in {self._reader.path}')
        if latched:
            self.get_logger().info(f'publishing {sorted(latched)} transient local, as recorded')
        return topics

    def _plan_times(self) -> tuple[int, int]:
        """First played bag time and the stamp shift between loop passes (ns)."""
        start = self._reader.start_time
        duration = self._reader.duration
        offset_ns = round(self.params['start_offset'] * 1e9)
        if offset_ns and offset_ns >= duration:
            raise ValueError(
                f"{NODE_NAME}: parameter 'start_offset' is {self.params['start_offset']} s but the bag "
                f'lasts {duration / 1e9:.3f} s'
            )
        count = max(self._reader.message_count, 2)
        # One mean message interval between passes, so the last message of a pass and the first
        # of the next are not stamped alike.
        gap = max(duration // (count - 1), 1)
        return start + offset_ns, max(duration - offset_ns, 0) + gap

    @property
    def played_topics(self) -> dict[str, str]:
        """``{published topic: message type}`` of everything this replayer publishes."""
        return {t.out_topic: t.msgtype for t in self._topics.values()}

    @property
    def bag_path(self) -> Path:
        return Path(self._reader.path)

    # -- control --

    def publish_diagnostics(self) -> None:
        """1 Hz status on /diagnostics (what was played, or why playback failed)."""
        if self.finished.is_set():
            state = 'finished'
        elif self.stats.started_wall is not None:
            state = 'playing'
        else:
            state = 'waiting to start'
        error = '' if self.error is None else f'{type(self.error).__name__}: {self.error}'
        self._diagnostics_pub.publish(
            replayer_array(
                self.get_name(),
                self.get_clock().now().to_msg(),
                dict(self.stats.published),
                self.stats.passes,
                self.stats.max_lag,
                state,
                error,
            )
        )

    def start(self) -> None:
        """Start playback (once)."""
        if not self._thread.is_alive() and not self.finished.is_set():
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop playback and wait for the thread to end."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def destroy_node(self) -> None:
        self.stop()
        with contextlib.suppress(Exception):  # already closed: nothing to release
            self._reader.close()
        super().destroy_node()

    # -- playback thread --

    def _run(self) -> None:
        try:
            self._wait_for_subscribers()
            if self.params['start_delay'] > 0:
                self._stop.wait(self.params['start_delay'])
            if not self._stop.is_set():
                self._play()
        except BaseException as exc:  # reported to whoever waits on finished
            self.error = exc
            self.get_logger().error(f'playback failed: {exc!r}')
        finally:
            self.stats.ended_wall = time.monotonic()
            total = sum(self.stats.published.values())
            paced = ''
            if self.pacer is not None and self.params['pace']:
                ps = self.pacer.stats
                paced = f'; the graph held it back {ps.pauses} times, {ps.paused_s:.1f} s in all'
                if ps.gave_up:  # said once as a warning when it happened; the summary says it too
                    paced += ', then pacing was switched off (no progress from the graph)'
            self.get_logger().info(
                f'playback ended: {total} messages in {self.stats.passes} pass(es), '
                f'max lag {self.stats.max_lag * 1e3:.1f} ms{paced}'
            )
            self.finished.set()
            if self._on_finished is not None:
                self._on_finished()

    def _play(self) -> None:
        rate = self.params['rate']
        connections = [c for t in self._topics.values() for c in t.connections]
        by_conn = {c.id: t for t in self._topics.values() for c in t.connections}
        self.stats.started_wall = wall0 = time.monotonic()
        deadline = wall0 + self.params['loop_seconds'] if self.params['loop_seconds'] > 0 else None
        t0 = self._play_start_ns
        pace_topic = self.params['pace_topic'] if self.params['pace'] else None
        pacer = self.pacer
        pass_index = 0
        while not self._stop.is_set():
            shift = pass_index * self._loop_period_ns
            messages = self._reader.messages(connections, start=self._play_start_ns)
            for conn, t_ns, raw in calibration_first(messages, lambda c: by_conn[c.id].msgtype):
                due = wall0 + (t_ns + shift - t0) / 1e9 / rate
                if deadline is not None and max(due, time.monotonic()) > deadline:
                    return  # wall time: a paced replay runs behind its schedule, and still stops
                if not self._sleep_until(due, t0, wall0, rate):
                    return
                topic = by_conn[conn.id]
                paced = pacer is not None and topic.out_topic == pace_topic
                # Never faster than the recorded rate; later when the graph is busy (the
                # schedule is kept, so a graph that catches up gets the recorded timing back).
                if paced and not pacer.before_image():
                    return
                self.stats.max_lag = max(self.stats.max_lag, time.monotonic() - due)
                data = bytes(raw)
                if shift and topic.stampable:
                    data = shift_header_stamp(data, shift)
                self._publish_clock(t_ns + shift)
                topic.publisher.publish(data)
                if paced and topic.stampable:
                    pacer.sent_image(header_stamp_ns(data))
                self.stats.published[topic.out_topic] += 1
            pass_index += 1
            self.stats.passes = pass_index
            if not self.params['loop']:
                break
        if self.params['linger'] > 0:
            self._stop.wait(self.params['linger'])

    def _sleep_until(self, due: float, t0: int, wall0: float, rate: float) -> bool:
        """Sleep until ``due`` (monotonic), ticking /clock meanwhile; False when stopped."""
        tick = 1.0 / self.params['clock_frequency']
        while True:
            now = time.monotonic()
            if now >= due:
                return not self._stop.is_set()
            if self._clock_pub is not None:
                self._publish_clock(t0 + int((now - wall0) * rate * 1e9))
                step = min(tick, due - now)
            else:
                step = due - now
            if self._stop.wait(step):
                return False

    def _publish_clock(self, t_ns: int) -> None:
        if self._clock_pub is None:
            return
        self._clock_msg.clock.sec, self._clock_msg.clock.nanosec = divmod(t_ns, 1_000_000_000)
        self._clock_pub.publish(self._clock_msg)

    def _wait_for_subscribers(self) -> None:
        count = self.params['wait_for_subscribers']
        nodes = non_empty(self.params['wait_for_nodes'])
        ready_nodes = non_empty(self.params['wait_ready'])
        if count <= 0 and not nodes and not ready_nodes:
            return
        wait_topics = set(non_empty(self.params['wait_topics']))
        played = {t.out_topic: t.publisher for t in self._topics.values()}
        # /clock may be waited for by name (a use_sim_time node must hear it from the start).
        pubs = {**played, '/clock': self._clock_pub} if self._clock_pub is not None else dict(played)
        unknown = wait_topics - set(pubs)
        if unknown:
            raise BagError(f"{NODE_NAME}: parameter 'wait_topics' names topics not played: {sorted(unknown)}")
        timeout = self.params['wait_timeout']
        deadline = time.monotonic() + timeout if timeout > 0 else None
        while not self._stop.is_set():
            missing = self._not_ready(pubs, wait_topics or set(played), count, nodes)
            missing = missing or self._not_ready_nodes(played, ready_nodes)
            if not missing:
                self._wait_warm(ready_nodes)
                return
            if deadline is not None and time.monotonic() > deadline:
                self.get_logger().warning(f'waited {timeout:g} s for subscribers, playing anyway: {missing}')
                return
            self._stop.wait(0.05)

    def _wait_warm(self, nodes: list[str]) -> None:
        """Up to ``wait_warm`` s for the ready ``nodes`` still warming up to say they are warm."""
        limit = float(self.params['wait_warm'])
        if limit <= 0 or not nodes or self.pacer is None:
            return
        cold = self.pacer.ready.cold(nodes)
        if not cold:
            return
        self.get_logger().info(f'waiting up to {limit:g} s for {", ".join(cold)} to warm up before playing')
        start = time.monotonic()
        while not self._stop.is_set() and (cold := self.pacer.ready.cold(nodes)):
            if time.monotonic() - start > limit:
                self.get_logger().warning(f'{", ".join(cold)} not warm after {limit:g} s: playing anyway')
                return
            self._stop.wait(0.05)
        if not cold:
            self.get_logger().info(f'graph warm after {time.monotonic() - start:.1f} s: playing')

    def _not_ready_nodes(self, pubs: dict[str, Any], nodes: list[str]) -> str:
        """What is missing before the ``wait_ready`` nodes can be fed ('' when nothing): their
        ready lines, then this replayer's publishers matched with every subscription they named."""
        if not nodes or self.pacer is None:
            return ''
        waiting = self.pacer.ready.missing(nodes)
        if waiting:
            return f'{", ".join(waiting)} not ready'
        for topic, pub in sorted(pubs.items()):
            wanted = self.pacer.ready.subscribers_of(topic, nodes)
            if pub.get_subscription_count() < wanted:
                return f'{topic} matched {pub.get_subscription_count()}/{wanted} ready subscribers'
        return ''

    def _not_ready(self, pubs: dict[str, Any], topics: set[str], count: int, nodes: list[str]) -> str:
        """What is still missing before playback may start ('' when nothing)."""
        for topic in sorted(topics):
            have = pubs[topic].get_subscription_count()
            if have < count:
                return f'{topic} has {have}/{count} subscribers'
        present = {
            (ns.rstrip('/') + '/' + name) if ns != '/' else '/' + name
            for name, ns in self.get_node_names_and_namespaces()
        }
        # Per played topic, how many of the awaited nodes subscribe to it: the publisher must be
        # matched at least that many times (other listeners may be matched already).
        needed: Counter[str] = Counter()
        for wanted in nodes:
            full = wanted if wanted.startswith('/') else '/' + wanted
            if full not in present:
                return f'node {wanted} not started'
            ns, _, name = full.rpartition('/')
            try:
                subs = self.get_subscriber_names_and_types_by_node(name, ns or '/')
            except Exception:  # the node left the graph meanwhile
                return f'node {wanted} not started'
            needed.update({topic for topic, _ in subs if topic in pubs})
        for topic, n in sorted(needed.items()):
            if pubs[topic].get_subscription_count() < n:
                return f'{topic} not yet matched with the nodes subscribing to it'
        return ''


# --- entry point --------------------------------------------------------------------------------


def main(args: list[str] | None = None) -> int:
    """``bag_replayer --ros-args -p bag:=PATH [-p rate:=0.5 ...]``: play, exit 0 at the end."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from .graph.dds import profile_for_console_node
    from .node_executor import executor_choice, make_node_executor, spin_until

    profile_line = profile_for_console_node()  # before rclpy.init: Fast DDS reads it once
    rclpy.init(args=args)
    logger = rclpy.logging.get_logger('bag_replayer')
    logger.info(profile_line)
    node = None
    try:
        # The console nodes' executor (node_executor.py): the graph's events reach the pacer
        # here several times a keyframe, and the single-threaded one rebuilds its wait set at
        # each wake-up.
        executor, line = make_node_executor(executor_choice())
        logger.info(line)
        node = BagReplayer()
        executor.add_node(node)
        spin_until(executor, lambda: rclpy.ok() and not node.finished.is_set(), timeout_sec=0.1)
        return 1 if node.error is not None else 0
    except (FileNotFoundError, ValueError) as exc:
        # The messages already name the node and the file or parameter: no traceback.
        print(f'error: {exc}', file=sys.stderr, flush=True)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    raise SystemExit(main())
