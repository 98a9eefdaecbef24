"""bag_replayer and recorder over real DDS: rate, offset, loop, remapping, /clock, errors, round trip.

Everything runs in this process (one rclpy context, one executor thread) except the console
entry point checks, which start ``bag_replayer`` as a subprocess like ``ros2 run`` would.
The bags are written here with rosbags: a few small images, camera infos and poses at 30 Hz.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402

from depth_fusion_ros.nodes.bag_replayer import (  # noqa: E402
    BagError,
    BagReplayer,
    header_stamp_ns,
    shift_header_stamp,
)
from depth_fusion_ros.nodes.recorder import Recorder  # noqa: E402

IMAGE = '/camera/rgb/image_color'
INFO = '/camera/rgb/camera_info'
POSE = '/camera/pose'
T0_NS = 1_700_000_000 * 1_000_000_000
PERIOD_NS = 33_333_333
POSE_TYPE = 'geometry_msgs/msg/PoseStamped'


# --- test bags ----------------------------------------------------------------------------------


def write_test_bag(path: Path, frames: int = 20, storage: str = 'mcap') -> Path:
    """A rosbag2 with ``frames`` 32x24 rgb8 images, camera infos and poses at 30 Hz.

    Each image is filled with its index so a received message tells which frame it was.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Header, Time = ts.types['std_msgs/msg/Header'], ts.types['builtin_interfaces/msg/Time']
    Image, CameraInfo = ts.types['sensor_msgs/msg/Image'], ts.types['sensor_msgs/msg/CameraInfo']
    RegionOfInterest = ts.types['sensor_msgs/msg/RegionOfInterest']
    PoseStamped, Pose = ts.types['geometry_msgs/msg/PoseStamped'], ts.types['geometry_msgs/msg/Pose']
    Point, Quaternion = ts.types['geometry_msgs/msg/Point'], ts.types['geometry_msgs/msg/Quaternion']
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {
            IMAGE: writer.add_connection(IMAGE, Image.__msgtype__, typestore=ts),
            INFO: writer.add_connection(INFO, CameraInfo.__msgtype__, typestore=ts),
            POSE: writer.add_connection(POSE, PoseStamped.__msgtype__, typestore=ts),
        }
        for i in range(frames):
            t = T0_NS + i * PERIOD_NS
            header = Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id='camera')
            image = Image(
                header=header,
                height=24,
                width=32,
                encoding='rgb8',
                is_bigendian=0,
                step=96,
                data=np.full(24 * 96, i, dtype=np.uint8),
            )
            info = CameraInfo(
                header=header,
                height=24,
                width=32,
                distortion_model='plumb_bob',
                d=np.zeros(5),
                k=np.array([30.0, 0, 16, 0, 30.0, 12, 0, 0, 1]),
                r=np.eye(3).ravel(),
                p=np.array([30.0, 0, 16, 0, 0, 30.0, 12, 0, 0, 0, 1, 0]),
                binning_x=0,
                binning_y=0,
                roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )
            pose = PoseStamped(
                header=Header(stamp=header.stamp, frame_id='world'),
                pose=Pose(
                    position=Point(x=0.01 * i, y=0.0, z=0.0), orientation=Quaternion(x=0, y=0, z=0, w=1)
                ),
            )
            for topic, msg in ((IMAGE, image), (INFO, info), (POSE, pose)):
                writer.write(conns[topic], t, ts.serialize_cdr(msg, msg.__msgtype__))
    return path


@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    return write_test_bag(tmp_path_factory.mktemp('bags') / 'small')


# --- ROS plumbing -------------------------------------------------------------------------------


@pytest.fixture(scope='module')
def context() -> Iterator[rclpy.context.Context]:
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


class Spinning:
    """Spins nodes in a background thread; destroys them on exit."""

    def __init__(self, context: rclpy.context.Context, *nodes) -> None:
        self.executor = SingleThreadedExecutor(context=context)
        self.nodes = list(nodes)
        for node in self.nodes:
            self.executor.add_node(node)
        self.thread = threading.Thread(target=self._spin, daemon=True)

    def _spin(self) -> None:
        with contextlib.suppress(Exception):  # the executor is shut down under us at the end
            self.executor.spin()

    def add(self, node) -> None:
        self.nodes.append(node)
        self.executor.add_node(node)

    def __enter__(self) -> Spinning:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        for node in self.nodes:
            node.destroy_node()
        self.thread.join(5.0)


class Listener:
    """Subscribes to topics and logs (arrival time, message) per topic."""

    def __init__(self, context, topics: dict[str, type], qos: QoSProfile | None = None) -> None:
        self.node = rclpy.create_node(f'listener_{os.getpid()}_{id(self)}', context=context)
        self.got: dict[str, list[tuple[float, object]]] = defaultdict(list)
        qos = qos or QoSProfile(depth=100)
        for topic, msg_cls in topics.items():
            self.node.create_subscription(
                msg_cls, topic, lambda m, t=topic: self.got[t].append((time.monotonic(), m)), qos
            )

    def settle(self, quiet: float = 1.0, timeout: float = 10.0) -> None:
        """Wait until nothing has arrived for ``quiet`` s (at most ``timeout`` s)."""
        start = time.monotonic()
        deadline = start + timeout
        while time.monotonic() < deadline:
            last = max((got[-1][0] for got in self.got.values() if got), default=start)
            last = max(last, start)
            if time.monotonic() - last >= quiet:
                return
            time.sleep(0.05)

    def stamps(self, topic: str) -> list[int]:
        return [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in self.got[topic]]


def make_replayer(context, bag: Path, **params) -> BagReplayer:
    """A replayer that waits for one subscriber on the image topic before playing."""
    params.setdefault('wait_for_subscribers', 1)
    params.setdefault('wait_topics', [params.get('remap_image', IMAGE)])
    params.pop('remap_image', None)
    params.setdefault('linger', 0.2)
    overrides = [Parameter('bag', value=str(bag))] + [Parameter(k, value=v) for k, v in params.items()]
    return BagReplayer(context=context, parameter_overrides=overrides, autostart=False)


def play(context, replayer: BagReplayer, listener: Listener, timeout: float = 20.0) -> None:
    with Spinning(context, listener.node, replayer):
        replayer.start()
        assert replayer.finished.wait(timeout), 'replayer did not finish'
        listener.settle()  # let the last messages arrive (slowly on a loaded machine)
    assert replayer.error is None


# --- tests --------------------------------------------------------------------------------------


def test_plays_every_message_in_order_and_ends(context, bag):
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo, Image

    listener = Listener(context, {IMAGE: Image, INFO: CameraInfo, POSE: PoseStamped})
    replayer = make_replayer(context, bag, rate=2.0)
    play(context, replayer, listener)
    assert listener.stamps(IMAGE) == [T0_NS + i * PERIOD_NS for i in range(20)]
    assert len(listener.got[INFO]) == 20 and len(listener.got[POSE]) == 20
    first = listener.got[IMAGE][3][1]
    assert (first.width, first.height, first.encoding) == (32, 24, 'rgb8')
    assert np.all(np.frombuffer(first.data, np.uint8) == 3)
    assert replayer.stats.published[IMAGE] == 20 and replayer.stats.passes == 1


def test_rate_scales_playback_time(context, bag):
    from sensor_msgs.msg import Image

    listener = Listener(context, {IMAGE: Image})
    replayer = make_replayer(context, bag, rate=0.5)
    play(context, replayer, listener)
    arrivals = [t for t, _ in listener.got[IMAGE]]
    span = arrivals[-1] - arrivals[0]
    expected = 19 * PERIOD_NS / 1e9 / 0.5  # 1.27 s at half speed
    # Never faster than scheduled; slower only by how far the player itself fell behind.
    assert span >= expected - 0.05
    assert span <= expected + replayer.stats.max_lag + 0.25


def test_start_offset_skips_the_beginning(context, bag):
    from sensor_msgs.msg import Image

    listener = Listener(context, {IMAGE: Image})
    replayer = make_replayer(context, bag, rate=4.0, start_offset=0.49)
    play(context, replayer, listener)
    # 0.49 s into a 30 Hz bag: frames 15 (at 0.4999 s) to 19
    assert listener.stamps(IMAGE) == [T0_NS + i * PERIOD_NS for i in range(15, 20)]


def test_loop_shifts_stamps_forward(context, bag):
    from sensor_msgs.msg import Image

    listener = Listener(context, {IMAGE: Image})
    # 20 frames at rate 10 last 0.06 s: 0.5 s of looping is several passes
    replayer = make_replayer(
        context, bag, rate=10.0, loop=True, loop_seconds=0.5, topics=[IMAGE], qos_depth=1000
    )
    play(context, replayer, listener)
    # Compared by stamp, not by arrival order: what matters is that no stamp repeats.
    received = sorted(zip(listener.stamps(IMAGE), listener.got[IMAGE], strict=True), key=lambda p: p[0])
    stamps = [s for s, _ in received]
    assert replayer.stats.passes >= 2 and len(stamps) > 20
    assert all(b > a for a, b in itertools.pairwise(stamps)), 'stamps must be shifted, never repeated'
    values = [int(np.frombuffer(m.data, np.uint8)[0]) for _, (_, m) in received]
    assert values[:21] == [*range(20), 0], values  # the second pass starts again at frame 0


def test_loop_seconds_is_wall_time_also_when_a_busy_graph_holds_the_replay(context, bag):
    from types import SimpleNamespace

    from sensor_msgs.msg import Image

    from depth_fusion_ros.nodes.pacer import PaceStats

    listener = Listener(context, {IMAGE: Image})
    replayer = make_replayer(
        context, bag, rate=10.0, loop=True, loop_seconds=0.5, topics=[IMAGE], qos_depth=1000, pace=True
    )
    # A graph that takes 0.2 s per image: the replay falls far behind its recorded schedule
    # (which, before, decided when to stop: 0.5 s of bag time took minutes of wall time).
    replayer.pacer = SimpleNamespace(
        before_image=lambda: time.sleep(0.2) is None,
        sent_image=lambda stamp: None,
        stats=PaceStats(),  # the real stats: the replayer reads every field
    )
    start = time.monotonic()
    play(context, replayer, listener)
    assert time.monotonic() - start < 5.0
    assert 1 <= len(listener.got[IMAGE]) <= 5


def test_remap_and_topic_selection(context, bag):
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image

    listener = Listener(context, {'/other/image': Image, IMAGE: Image, POSE: PoseStamped})
    replayer = make_replayer(
        context,
        bag,
        rate=4.0,
        topics=[IMAGE],
        remap=[f'{IMAGE}:=/other/image'],
        remap_image='/other/image',
    )
    assert replayer.played_topics == {'/other/image': 'sensor_msgs/msg/Image'}
    play(context, replayer, listener)
    assert len(listener.got['/other/image']) == 20
    assert not listener.got[IMAGE] and not listener.got[POSE]


def test_publish_clock_follows_bag_time(context, bag):
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    listener = Listener(context, {IMAGE: Image})
    clocks = Listener(context, {'/clock': Clock}, qos=qos)
    replayer = make_replayer(context, bag, rate=2.0, publish_clock=True)
    with Spinning(context, listener.node, clocks.node, replayer):
        replayer.start()
        assert replayer.finished.wait(20.0)
        clocks.settle()
    values = [m.clock.sec * 10**9 + m.clock.nanosec for _, m in clocks.got['/clock']]
    assert len(values) >= 20
    assert min(values) >= T0_NS and max(values) <= T0_NS + 19 * PERIOD_NS
    assert values == sorted(values), '/clock must not go backwards'


def test_use_sim_time_node_sees_bag_time(context, bag):
    from sensor_msgs.msg import Image

    sim = rclpy.create_node(
        'sim_time_user', context=context, parameter_overrides=[Parameter('use_sim_time', value=True)]
    )
    seen: list[int] = []
    sim.create_subscription(Image, IMAGE, lambda m: seen.append(sim.get_clock().now().nanoseconds), 10)
    replayer = make_replayer(context, bag, rate=2.0, publish_clock=True, wait_topics=[IMAGE, '/clock'])
    with Spinning(context, sim, replayer):
        replayer.start()
        assert replayer.finished.wait(20.0)
        time.sleep(0.3)
    assert seen and all(T0_NS - 10**9 < t <= T0_NS + 20 * PERIOD_NS for t in seen[1:])


def test_wait_for_subscribers_holds_playback(context, bag):
    from sensor_msgs.msg import Image

    replayer = make_replayer(context, bag, rate=4.0)
    with Spinning(context, replayer) as spin:
        replayer.start()
        time.sleep(0.5)
        assert replayer.stats.published[IMAGE] == 0, 'played before anyone listened'
        listener = Listener(context, {IMAGE: Image})
        spin.add(listener.node)
        assert replayer.finished.wait(20.0)
        listener.settle()
    assert len(listener.got[IMAGE]) == 20


def test_bad_bag_paths_raise_clear_errors(context, tmp_path):
    with pytest.raises(FileNotFoundError, match='does not exist'):
        make_replayer(context, tmp_path / 'nope')
    (tmp_path / 'notes.txt').write_text('x')
    with pytest.raises(BagError, match='unknown storage'):
        make_replayer(context, tmp_path / 'notes.txt')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(BagError, match=r'without metadata\.yaml'):
        make_replayer(context, tmp_path / 'empty')
    broken = tmp_path / 'broken'
    broken.mkdir()
    (broken / 'metadata.yaml').write_text(
        'rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: zip\n'
    )
    with pytest.raises(BagError, match='cannot read bag'):
        make_replayer(context, broken)


def test_bad_parameters_raise_clear_errors(context, bag):
    with pytest.raises(ValueError, match='start_offset'):
        make_replayer(context, bag, start_offset=5.0)
    with pytest.raises(ValueError, match='rate'):
        make_replayer(context, bag, rate=0.0)
    with pytest.raises(ValueError, match='remap'):
        make_replayer(context, bag, remap=['/a=/b'])
    with pytest.raises(BagError, match='not in'):
        make_replayer(context, bag, topics=['/missing'])


def test_stamp_patch_round_trip():
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Header, Time = ts.types['std_msgs/msg/Header'], ts.types['builtin_interfaces/msg/Time']
    msg = Header(stamp=Time(sec=5, nanosec=999_999_999), frame_id='f')
    raw = bytes(ts.serialize_cdr(msg, 'std_msgs/msg/Header'))
    shifted = shift_header_stamp(raw, 2)
    assert header_stamp_ns(shifted) == 6 * 10**9 + 1
    back = ts.deserialize_cdr(shifted, 'std_msgs/msg/Header')
    assert (back.stamp.sec, back.stamp.nanosec, back.frame_id) == (6, 1, 'f')


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_recorder_round_trip(context, bag, tmp_path, storage):
    """What the replayer plays, the recorder writes byte for byte, and it deserializes."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    out = tmp_path / f'rec_{storage}'
    recorder = Recorder(
        context=context,
        output=out,
        topics={IMAGE: 'sensor_msgs/msg/Image', POSE: ''},  # POSE's type found from the graph
        parameter_overrides=[Parameter('storage', value=storage)],
    )
    replayer = make_replayer(context, bag, rate=4.0, wait_topics=[IMAGE, POSE])
    with Spinning(context, recorder, replayer):
        replayer.start()
        assert replayer.finished.wait(20.0)
        deadline = time.monotonic() + 5.0
        while recorder.counts[IMAGE] + recorder.counts[POSE] < 40 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert recorder.staging.exists() and not out.exists()
        assert recorder.close(success=True) == out
    assert not recorder.staging.exists()
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as src:
        original = {(c.topic, header_stamp_ns(raw)): raw for c, _, raw in src.messages()}
    with Reader(out) as rec:
        assert {c.topic: c.msgtype for c in rec.connections} == {
            IMAGE: 'sensor_msgs/msg/Image',
            POSE: 'geometry_msgs/msg/PoseStamped',
        }
        assert rec.message_count == 40
        for conn, _, raw in rec.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            assert msg.header.frame_id in ('camera', 'world')
            assert bytes(raw) == bytes(original[(conn.topic, header_stamp_ns(raw))])
    assert recorder.stamp_logs[IMAGE].stamps() == [T0_NS + i * PERIOD_NS for i in range(20)]


def _wait_for(condition, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


def test_a_latched_topic_stays_latched_through_a_recording_and_its_replay(context, bag, tmp_path):
    """Transient-local topics published before the recorder existed are recorded (a named one
    and one whose publishers the recorder found latched), the bag says so, and the replay
    publishes them latched again: a transient-local subscriber that joins after the replay has
    played them still gets every one. A bag that recorded no QoS plays volatile, as before."""
    from geometry_msgs.msg import TransformStamped
    from rosbags.rosbag2 import Reader

    from depth_fusion_ros.data.bag_qos import recorded_latched_depth
    from depth_fusion_ros.nodes.qos import latched_qos

    named, found = '/latched_test/named', '/latched_test/found'
    source = rclpy.create_node(f'latched_source_{os.getpid()}', context=context)
    pubs = {t: source.create_publisher(TransformStamped, t, latched_qos(8)) for t in (named, found)}
    for sec in (1, 2, 3):
        for topic, pub in pubs.items():
            msg = TransformStamped()
            msg.header.stamp.sec = sec
            msg.child_frame_id = topic
            pub.publish(msg)
    out = tmp_path / 'latched_rec'
    recorder = Recorder(
        context=context,
        output=out,
        topics={named: 'geometry_msgs/msg/TransformStamped', found: ''},
        latched=[named],
    )
    with Spinning(context, source, recorder):
        assert _wait_for(lambda: recorder.counts[named] == 3 and recorder.counts[found] == 3)
        assert recorder.close(success=True) == out
    with Reader(out) as rec:
        kept = {c.topic: recorded_latched_depth(c) for c in rec.connections}
    assert kept == {named: 100, found: 100}  # the recorder's qos_depth
    with Reader(bag) as plain:
        assert {recorded_latched_depth(c) for c in plain.connections} == {0}

    replayer = make_replayer(context, out, wait_for_subscribers=0)
    with Spinning(context, replayer) as spinning:
        replayer.start()
        assert replayer.finished.wait(20.0) and replayer.error is None
        assert sum(replayer.stats.published.values()) == 6  # played before anyone listened
        late = Listener(context, {named: TransformStamped, found: TransformStamped}, latched_qos(8))
        spinning.add(late.node)
        assert _wait_for(lambda: len(late.got[named]) == 3 and len(late.got[found]) == 3)
    for topic in (named, found):
        assert [m.header.stamp.sec for _, m in late.got[topic]] == [1, 2, 3]


def test_recorder_refuses_existing_output(context, tmp_path):
    (tmp_path / 'taken').mkdir()
    with pytest.raises(ValueError, match='already exists'):
        Recorder(context=context, output=tmp_path / 'taken', topics={IMAGE: 'sensor_msgs/msg/Image'})
    with pytest.raises(ValueError, match='unknown'):
        Recorder(context=context, output=tmp_path / 'new', topics={IMAGE: 'sensor_msgs/msg/Nope'})
    assert not (tmp_path / 'new.partial').exists()


def test_console_script_plays_to_the_end_and_reports_bad_bags(bag, tmp_path):
    """``bag_replayer`` as a process: exit 0 at the end of the bag, 1 with a message on a bad path."""
    cmd = [sys.executable, '-m', 'depth_fusion_ros.nodes.bag_replayer', '--ros-args']
    ok = subprocess.run(
        [*cmd, '-p', f'bag:={bag}', '-p', 'rate:=10.0', '-p', 'linger:=0.0'],
        capture_output=True,
        text=True,
        timeout=60,
        env=os.environ.copy(),
    )
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert 'playback ended: 60 messages' in ok.stdout + ok.stderr
    bad = subprocess.run(
        [*cmd, '-p', f'bag:={tmp_path / "missing_bag"}'], capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 1
    assert f'bag {tmp_path / "missing_bag"} does not exist' in bad.stderr


def test_same_instant_messages_play_calibration_first():
    """An image stored before its camera_info of the same instant is played after it."""
    from depth_fusion_ros.nodes.bag_replayer import calibration_first

    types = {'img': 'sensor_msgs/msg/Image', 'info': 'sensor_msgs/msg/CameraInfo', 'pose': POSE_TYPE}
    stored = [('img', 1, 'a'), ('info', 1, 'b'), ('pose', 1, 'c'), ('img', 2, 'd'), ('pose', 2, 'e')]
    played = list(calibration_first(iter(stored), types.get))
    assert [(c, t) for c, t, _ in played] == [('info', 1), ('pose', 1), ('img', 1), ('pose', 2), ('img', 2)]


def test_wait_warm_holds_the_replay_until_a_warming_node_is_warm(context, bag):
    """A node ready while it warms up (fusion kernels compiling) says ``warm: false``; with
    ``wait_warm`` the replayer plays only after its warm line; the watcher keeps both."""
    from sensor_msgs.msg import Image

    from depth_fusion_ros.nodes.graph_events import GraphEvents, ReadyStatus

    warming = rclpy.create_node(f'warming_{os.getpid()}', context=context)
    warming.create_subscription(Image, IMAGE, lambda m: None, QoSProfile(depth=10))
    events = GraphEvents(warming)
    listener = Listener(context, {IMAGE: Image})
    replayer = make_replayer(context, bag, rate=4.0, wait_ready=[warming.get_name()], wait_warm=30.0)
    warm_at: list[float] = []

    def warm_later() -> None:
        time.sleep(1.5)
        warm_at.append(time.monotonic())
        events.warm('kernels built: warm')

    with Spinning(context, listener.node, replayer, warming):
        status = events.ready(warm=False)
        assert not status.warm and ReadyStatus.from_json(status.to_json()) == status
        threading.Thread(target=warm_later, daemon=True).start()
        replayer.start()
        assert replayer.finished.wait(30.0), 'replayer did not finish'
        listener.settle()
        name = warming.get_fully_qualified_name()
        assert replayer.pacer.ready.statuses[name].warm is False  # the ready line stays the first
        assert replayer.pacer.ready.warm_statuses[name].warm and not replayer.pacer.ready.cold([name])
    assert replayer.error is None and len(listener.got[IMAGE]) == 20
    assert listener.got[IMAGE][0][0] >= warm_at[0]  # not one image before the warm line


def test_ready_lines_without_warm_are_warm_and_a_warm_line_before_ready_makes_it_warm(context):
    from depth_fusion_ros.nodes.graph_events import GraphEvents, ReadyStatus

    legacy = ReadyStatus.from_json('{"node": "/n", "subscribes": ["/a"], "seconds": 1.5}')
    assert legacy.warm and legacy.subscribes == ('/a',)
    node = rclpy.create_node(f'early_{os.getpid()}', context=context)
    try:
        events = GraphEvents(node)
        assert events.warm() is None  # nothing published before the ready line
        assert events.ready(subscribes=['/a'], warm=False).warm  # the warm-up finished first
    finally:
        node.destroy_node()
