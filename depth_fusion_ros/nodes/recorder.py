"""``recorder``: writes ROS topics into a rosbag2 (mcap or sqlite3) with rosbags.

Why our own recorder: ``ros2 bag record`` is not available from pip. Subscriptions are created
with ``raw=True``, so rclpy hands over the serialized CDR bytes and they go into the bag as
they are (no deserialization, no re-encoding).

The bag is written under a staging folder ``OUT.partial/`` and moved to ``OUT`` only by
``close(success=True)``: a run that crashed or was interrupted never leaves a half-written
bag under the name a user (or the demo) will read. What such a run left in ``OUT.partial/``
stays: a recorder for the same ``OUT`` refuses to start (``data/staging.py``).

Besides writing, the recorder remembers the header stamp and the arrival time of every
message per topic (bounded), which is what ``depth-fusion run`` needs to know when every
keyframe's fused output has arrived, and what the node-graph benchmark needs for latency.
"""

from __future__ import annotations

import queue
import shutil
import sys
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node

from ..data.bag_qos import latched_bag_qos
from ..data.cdr_stamps import has_leading_header, header_stamp_ns
from ..data.staging import check_no_unfinished_recording, staging_folder
from .bag_replayer import non_empty, ros_message_class
from .params import ParamSpec, declare_parameters
from .qos import QOS_CHOICES, latched_qos, offers_latched, qos_profile

NODE_NAME = 'recorder'

#: Entries of stamp -> arrival time kept per topic: hours of keyframes, a few MB at most.
MAX_TRACKED_STAMPS = 100_000

RECORDER_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec('output', '', 'rosbag2 folder to write; must not exist yet'),
    ParamSpec(
        'topics', [''], "topics to record, as 'name:package/msg/Type' (or 'name' when a publisher exists)"
    ),
    ParamSpec('storage', 'mcap', 'rosbag2 storage of the output', choices=('mcap', 'sqlite3')),
    ParamSpec('qos', 'reliable', 'QoS of the subscriptions (must match the publishers)', choices=QOS_CHOICES),
    ParamSpec('qos_depth', 100, 'history depth of each subscription', 1, 100000),
    ParamSpec(
        'latched_topics',
        [''],
        'topics subscribed transient local and recorded so (replayed so by bag_replayer); their '
        'publishers must be transient local too (DDS matches no volatile one); a topic whose type '
        'comes from the graph is latched when all its publishers are',
    ),
)


def parse_topic_specs(items: list[str]) -> dict[str, str]:
    """``['/a:sensor_msgs/msg/Image', '/b']`` -> ``{'/a': 'sensor_msgs/msg/Image', '/b': ''}``."""
    topics: dict[str, str] = {}
    for item in non_empty(items):
        name, _, msgtype = item.partition(':')
        if not name.startswith('/'):
            raise ValueError(f"{NODE_NAME}: parameter 'topics': {item!r} must be an absolute topic name")
        if msgtype and msgtype.count('/') != 2:
            raise ValueError(f"{NODE_NAME}: parameter 'topics': {item!r}: type must look like pkg/msg/Type")
        topics[name] = msgtype
    return topics


def check_message_type(topic: str, msgtype: str) -> None:
    """``ValueError`` unless ``msgtype`` is empty (resolved later) or an installed message type."""
    if not msgtype:
        return
    try:
        ros_message_class(msgtype)
    except (ImportError, AttributeError, ValueError):
        raise ValueError(f'{NODE_NAME}: cannot record {topic}: message type {msgtype} is unknown') from None


class StampLog:
    """Arrival time (``time.monotonic``) of each header stamp of one topic, oldest dropped first."""

    def __init__(self, limit: int = MAX_TRACKED_STAMPS) -> None:
        self._times: OrderedDict[int, float] = OrderedDict()
        self._limit = limit

    def add(self, stamp_ns: int, arrival: float) -> None:
        self._times.setdefault(stamp_ns, arrival)
        while len(self._times) > self._limit:
            self._times.popitem(last=False)

    def __contains__(self, stamp_ns: int) -> bool:
        return stamp_ns in self._times

    def __len__(self) -> int:
        return len(self._times)

    def stamps(self) -> list[int]:
        return list(self._times)

    def arrival(self, stamp_ns: int) -> float | None:
        return self._times.get(stamp_ns)


class BagWriterThread:
    """Owns a rosbags ``Writer`` on one thread and writes what the callbacks queue.

    Why a thread: the sqlite3 storage binds its connection to the thread that opened it (an
    executor runs callbacks on any of its threads), and disk writes then never stall the
    executor. The queue is bounded, so a slow disk slows the callbacks instead of growing memory.
    """

    def __init__(self, path: Path, storage: str, max_queue: int = 256) -> None:
        self.path = path
        self.storage = storage
        self.written: Counter[str] = Counter()
        self.error: BaseException | None = None
        self._queue: queue.Queue[tuple] = queue.Queue(maxsize=max_queue)
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._run, name='bag_writer', daemon=True)
        self._thread.start()
        self._opened.wait()
        if self.error is not None:
            raise ValueError(f'{NODE_NAME}: cannot write {path}: {self.error}') from None

    def add_connection(self, topic: str, msgtype: str, latched_depth: int = 0) -> None:
        """A topic to write; ``latched_depth`` > 0 records it as offered transient local."""
        self._queue.put(('connection', topic, msgtype, latched_depth))

    def write(self, topic: str, stamp_ns: int, raw: bytes) -> None:
        self._queue.put(('message', topic, stamp_ns, raw))

    def close(self, timeout: float = 60.0) -> None:
        """Write what is queued, close the bag; raises if anything failed on the thread."""
        self._queue.put(('close',))
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise RuntimeError(f'{NODE_NAME}: writing {self.path} did not finish within {timeout:g} s')
        if self.error is not None:
            raise RuntimeError(f'{NODE_NAME}: writing {self.path} failed: {self.error!r}')

    def _run(self) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        plugin = StoragePlugin.MCAP if self.storage == 'mcap' else StoragePlugin.SQLITE3
        try:
            writer = Writer(self.path, version=9, storage_plugin=plugin)
            writer.open()
        except Exception as exc:  # reported by the constructor
            self.error = exc
            self._opened.set()
            return
        self._opened.set()
        typestore = get_typestore(Stores.ROS2_JAZZY)
        connections: dict[str, Any] = {}
        try:
            while True:
                item = self._queue.get()
                if item[0] == 'close':
                    break
                if self.error is not None:
                    continue  # keep draining so producers never block on a dead writer
                try:
                    if item[0] == 'connection':
                        qos = [latched_bag_qos(item[3])] if item[3] else []
                        connections[item[1]] = writer.add_connection(
                            item[1], item[2], typestore=typestore, offered_qos_profiles=qos
                        )
                    else:
                        writer.write(connections[item[1]], item[2], item[3])
                        self.written[item[1]] += 1
                except Exception as exc:  # disk full, ...: remembered, raised by close()
                    self.error = exc
        finally:
            try:
                writer.close()
            except Exception as exc:
                self.error = self.error or exc


class Recorder(Node):
    """Records ``topics`` to ``output`` (parameters, or the keyword arguments that override them).

    ``topics`` maps each topic to its type (``''``: taken from the graph once a publisher
    exists). ``latched`` (or the parameter ``latched_topics``) names topics whose publishers keep
    their last messages (transient local): they are subscribed so, and the bag says so, so a
    replay publishes them so. ``watch`` names topics whose stamps are logged like the recorded ones but whose
    messages are not written (e.g. the input images, to measure latency without storing them).
    With ``track_only`` nothing is written at all (no bag): every topic is only watched.
    """

    def __init__(
        self,
        *,
        output: str | Path | None = None,
        topics: Mapping[str, str] | None = None,
        watch: Mapping[str, str] | None = None,
        latched: Iterable[str] | None = None,
        track_only: bool = False,
        node_name: str = NODE_NAME,
        **kwargs: Any,
    ) -> None:
        super().__init__(node_name, **kwargs)
        self.params = declare_parameters(self, RECORDER_PARAMS)
        wanted = dict(topics) if topics is not None else parse_topic_specs(self.params['topics'])
        if not wanted:
            raise ValueError(f"{NODE_NAME}: nothing to record: parameter 'topics' is empty")
        watch = {**(watch or {}), **wanted} if track_only else dict(watch or {})
        if track_only:
            wanted = {}
        for topic, msgtype in {**watch, **wanted}.items():
            check_message_type(topic, msgtype)
        out = Path(output if output is not None else self.params['output'])
        if not track_only and (not str(out) or str(out) == '.'):
            raise ValueError(f"{NODE_NAME}: parameter 'output' is empty: give the bag folder to write")
        self.output: Path | None = None if track_only else out
        self.staging = staging_folder(out) if not track_only else Path()
        self.counts: Counter[str] = Counter()
        self.stamp_logs: dict[str, StampLog] = {}
        self.last_arrival = time.monotonic()
        self.closed = False
        self._lock = threading.Lock()
        self._group = MutuallyExclusiveCallbackGroup()
        self._qos = qos_profile(self.params['qos'], self.params['qos_depth'])
        self._latched = set(latched if latched is not None else non_empty(self.params['latched_topics']))
        self._record_subs: dict[str, Any] = {}
        self._written_topics: set[str] = set()
        self._pending: dict[str, tuple[str, bool]] = {t: (m, False) for t, m in watch.items()}
        self._pending.update({t: (m, True) for t, m in wanted.items()})
        self._writer = None if track_only else self._open_writer()
        self._discovery_timer: Any = None
        self._subscribe_pending()
        if self._pending:
            # Types not given: resolved from the graph once a publisher shows up.
            self._discovery_timer = self.create_timer(
                0.2, self._subscribe_pending, callback_group=self._group
            )
        if wanted:
            self.get_logger().info(f'recording {sorted(wanted)} to {out}')

    # -- set-up --

    def _open_writer(self) -> BagWriterThread:
        assert self.output is not None
        if self.output.exists():
            raise ValueError(f'{NODE_NAME}: {self.output} already exists: remove it or choose another output')
        check_no_unfinished_recording(self.output)  # it was removed here, and so lost
        self.staging.mkdir(parents=True)
        try:
            return BagWriterThread(self.staging / self.output.name, self.params['storage'])
        except ValueError:
            shutil.rmtree(self.staging, ignore_errors=True)
            raise

    def _subscribe_pending(self) -> None:
        if not self._pending:
            return
        graph = dict(self.get_topic_names_and_types())
        for topic, (msgtype, write) in list(self._pending.items()):
            if not msgtype:
                types = graph.get(topic)
                if not types:
                    continue
                msgtype = types[0]
                if self._publishers_latched(topic):
                    self._latched.add(topic)
            self._subscribe(topic, msgtype, write)
            del self._pending[topic]
        if not self._pending and self._discovery_timer is not None:
            self._discovery_timer.cancel()

    def _publishers_latched(self, topic: str) -> bool:
        """Every publisher of ``topic`` offers transient local, as ``ros2 bag record`` checks."""
        infos = self.get_publishers_info_by_topic(topic)
        return bool(infos) and all(offers_latched(i) for i in infos)

    def _subscribe(self, topic: str, msgtype: str, write: bool) -> None:
        msg_cls = ros_message_class(msgtype)
        latched = topic in self._latched
        depth = self.params['qos_depth']
        if write:
            self._writer.add_connection(topic, msgtype, depth if latched else 0)
            self._written_topics.add(topic)
        self.stamp_logs[topic] = StampLog()
        stampable = has_leading_header(msgtype)
        self._record_subs[topic] = self.create_subscription(
            msg_cls,
            topic,
            lambda raw, t=topic, w=write, s=stampable: self._on_message(t, raw, w, s),
            latched_qos(depth) if latched else self._qos,
            callback_group=self._group,
            raw=True,
        )

    # -- receiving --

    def _on_message(self, topic: str, raw: bytes, write: bool, stampable: bool) -> None:
        arrival = time.monotonic()
        with self._lock:
            if self.closed:
                return
            if write:
                self._writer.write(topic, self.get_clock().now().nanoseconds, raw)
            self.counts[topic] += 1
            if stampable:
                self.stamp_logs[topic].add(header_stamp_ns(raw), arrival)
            self.last_arrival = arrival

    @property
    def recorded_topics(self) -> list[str]:
        """Topics being written (those whose type is known by now)."""
        return sorted(self._written_topics)

    @property
    def waiting_topics(self) -> list[str]:
        """Topics not subscribed yet because no publisher told their type."""
        return sorted(self._pending)

    # -- closing --

    def close(self, success: bool = True) -> Path | None:
        """Close the bag; on success move it to ``output`` and return that, else the staging path.

        A failure of the writer thread (e.g. disk full) raises ``RuntimeError`` and leaves the
        bag in the staging folder. Returns ``None`` when tracking only (no bag).
        """
        with self._lock:
            already = self.closed
            self.closed = True
        if self._writer is None or self.output is None:
            return None
        if already:
            return self.output if self.output.exists() else self.staging / self.output.name
        self._writer.close()
        if not success:
            self.get_logger().warning(f'incomplete recording left in {self.staging}')
            return self.staging / self.output.name
        (self.staging / self.output.name).rename(self.output)
        self.staging.rmdir()
        total = sum(self._writer.written.values())
        self.get_logger().info(f'wrote {total} messages to {self.output}')
        return self.output

    def destroy_node(self) -> None:
        if not self.closed:
            try:
                self.close(success=False)
            except RuntimeError as exc:
                self.get_logger().error(str(exc))
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """``python -m depth_fusion_ros.nodes.recorder --ros-args -p output:=OUT -p topics:=[...]``.

    Records until Ctrl-C, then closes the bag under its final name.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from .node_executor import executor_choice, make_node_executor, spin_until

    rclpy.init(args=args)
    node = None
    try:
        # The console nodes' executor (node_executor.py: the single-threaded one rebuilds its
        # wait set at every message), spun so that Ctrl-C is noticed (its spin() would not).
        executor, line = make_node_executor(executor_choice())
        rclpy.logging.get_logger('recorder').info(line)
        node = Recorder()
        executor.add_node(node)
        spin_until(executor, rclpy.ok)
    except (FileNotFoundError, ValueError) as exc:
        print(f'error: {exc}', file=sys.stderr, flush=True)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.close(success=True)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
