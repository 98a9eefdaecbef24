"""TUM folder / ROS 1 bag -> rosbag2 (mcap and sqlite3) -> read back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from message_kinds import odometry_msg
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_tum import make_tum_folder, write_camera_yaml

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.cli.main import main as cli_main
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data import tum_to_bag
from depth_fusion_ros.data.bag_writer import AtomicBagWriter
from depth_fusion_ros.data.compressed import compressed_image_msg
from depth_fusion_ros.data.rosbag_convert import (
    BagTopics,
    TfTree,
    convert,
    recorded_to_rosbag2,
    tum_to_rosbag,
)
from depth_fusion_ros.data.rosbag_read import (
    bag_topics,
    bag_typestore,
    iter_messages,
    load_bag_sequence,
    read_depth_images,
    read_poses,
)
from depth_fusion_ros.data.tum import associate, load_tum_sequence, read_groundtruth, read_tum_index
from depth_fusion_ros.data.undistort import CameraCalibration
from depth_fusion_ros.geometry import make_pose

RGB, INFO, DEPTH, POSE = (
    '/camera/rgb/image_color',
    '/camera/rgb/camera_info',
    '/camera/depth/image',
    '/camera/pose',
)
DISTORTION = (0.05, -0.02, 0.001, 0.0005, 0.0)


def _raw_messages(bag: Path) -> list[tuple[str, int, bytes]]:
    with Reader(bag) as reader:
        return [(c.topic, t, bytes(raw)) for c, t, raw in reader.messages()]


def _rows_in_span(stamps_ns: np.ndarray, first_ns: int, last_ns: int) -> np.ndarray:
    """Which of a pose source's samples a bag must carry: from the last one at or before the
    first frame - 0.5 s to the first one at or after the last frame + 0.5 s (clipped)."""
    before = stamps_ns[stamps_ns <= first_ns - 500_000_000]
    after = stamps_ns[stamps_ns >= last_ns + 500_000_000]
    lo = before.max() if len(before) else stamps_ns.min()
    hi = after.min() if len(after) else stamps_ns.max()
    return (stamps_ns >= lo) & (stamps_ns <= hi)


def _check_own_samples(bag: Path, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """The bag's pose topic is exactly these samples: stamps, poses (1e-9), header = bag time."""
    got_stamps, got_poses = read_poses(bag)
    assert got_stamps.tolist() == stamps_ns.tolist()
    np.testing.assert_allclose(got_poses, poses, atol=1e-9)
    for _, bag_time, msg in iter_messages(bag, [POSE]):
        assert m.stamp_to_ns(msg.header.stamp) == bag_time and msg.header.frame_id == 'world'


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_tum_folder_round_trip(tmp_path, storage):
    src = tmp_path / 'tum'
    make_tum_folder(src, n=5, D=DISTORTION)
    out = tmp_path / f'bag_{storage}'
    result = tum_to_rosbag(src, out, storage=storage, show_progress=False)
    expected = {f.stamp_ns: f for f in associate(read_tum_index(src)).frames}
    gt = read_groundtruth(src / 'groundtruth.txt')
    rows = _rows_in_span(gt.stamps_ns, min(expected), max(expected))
    assert result.frames == 5 and result.messages == {RGB: 5, INFO: 5, DEPTH: 5, POSE: int(rows.sum())}
    assert result.pose_source == 'groundtruth.txt, its own samples'
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(['tum', out.name])  # no partial left

    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image

    seen = {RGB: [], DEPTH: [], POSE: [], INFO: []}
    for topic, bag_time, raw in _raw_messages(out):
        seen[topic].append(bag_time)
        if topic == RGB:
            ros = deserialize_message(raw, Image)  # rclpy decodes the bag's bytes
            assert m.stamp_to_ns(ros.header.stamp) == bag_time
            assert ros.encoding == 'rgb8' and ros.header.frame_id == 'camera_rgb_optical_frame'
            original = cv2.cvtColor(cv2.imread(str(expected[bag_time].rgb_file)), cv2.COLOR_BGR2RGB)
            np.testing.assert_array_equal(m.image_to_rgb(ros), original)  # raw, not undistorted
        elif topic == DEPTH:
            ros = deserialize_message(raw, Image)
            raw_png = cv2.imread(str(expected[bag_time].depth_file), cv2.IMREAD_UNCHANGED)
            depth = m.image_to_numpy(ros)
            np.testing.assert_array_equal(np.isnan(depth), raw_png == 0)
            np.testing.assert_array_equal(depth[raw_png > 0], raw_png[raw_png > 0].astype(np.float32) / 5000)
    assert all(sorted(seen[topic]) == sorted(expected) for topic in (RGB, DEPTH, INFO))
    assert sorted(seen[POSE]) == gt.stamps_ns[rows].tolist()  # the 100 Hz rows, at their own stamps
    _check_own_samples(out, gt.stamps_ns[rows], gt.poses[rows])
    bag = load_bag_sequence(out, width=32, height=24)  # read at the images, the frames' poses
    for f in bag.frames:
        np.testing.assert_allclose(f.pose, expected[round(f.stamp * 1e9)].pose, atol=1e-9)
    for _, _, info in iter_messages(out, [INFO]):
        calib = m.camera_info_to_calibration(info)
        assert calib.D == DISTORTION and calib.camera == read_tum_index(src).calibration.camera


def test_bag_sequence_equals_folder_sequence(tmp_path):
    src = tmp_path / 'tum'
    make_tum_folder(src, n=4, D=DISTORTION)
    out = tmp_path / 'bag'
    tum_to_rosbag(src, out, show_progress=False)
    folder = load_tum_sequence(src, width=32, height=24)
    bag = load_bag_sequence(out, width=32, height=24)
    assert len(bag) == len(folder) == 4 and bag.camera == folder.camera and bag.gt_camera == folder.gt_camera
    for a, b in zip(folder.frames, bag.frames, strict=True):
        assert a.stamp == b.stamp
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)  # NaN in the same places
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-9)
    assert len(load_bag_sequence(out, max_frames=2)) == 2
    # A colour calibration's depth-camera centre registers a folder's depth; a bag's depth is
    # registered already, so the centre would do nothing there: an error, not an ignored option.
    beside = CameraCalibration(bag.gt_camera, centre_in_depth_camera=(0.025, 0.0, 0.0))
    with pytest.raises(ValueError, match="bag's depth is read as registered"):
        load_bag_sequence(out, width=32, height=24, calibration=beside)
    depth = read_depth_images(out, DEPTH)
    assert sorted(depth) == [round(f.stamp * 1e9) for f in folder.frames]
    with pytest.raises(ValueError, match=r'no topic /nope \(it has: /camera/depth/image'):
        read_depth_images(out, '/nope')


def test_tum_pose_topic_holds_the_groundtruths_own_rows_around_the_frames(tmp_path):
    """groundtruth.txt at 100 Hz from 98 s to 103 s, images at 10 Hz from 100 s: the bag carries
    the motion capture's own rows from 99.5 s to 100.9 s (the frames +- 0.5 s), and read at the
    images they give the folder's poses."""
    src = tmp_path / 'tum'
    make_tum_folder(src, n=5, gt_span=(98.0, 103.0), D=DISTORTION)
    gt = read_groundtruth(src / 'groundtruth.txt')
    out = tmp_path / 'bag'
    result = tum_to_rosbag(src, out, show_progress=False)
    rows = _rows_in_span(gt.stamps_ns, 100_000_000_000, 100_400_000_000)
    assert gt.stamps_ns[rows][[0, -1]].tolist() == [99_500_000_000, 100_900_000_000] and rows.sum() == 141
    assert result.frames == 5 and result.messages[POSE] == 141 and len(gt) == 500
    _check_own_samples(out, gt.stamps_ns[rows], gt.poses[rows])
    folder = load_tum_sequence(src, width=32, height=24)
    bag = load_bag_sequence(out, width=32, height=24)
    assert bag.stamps.tolist() == folder.stamps.tolist() and bag.dropped == folder.dropped == {}
    np.testing.assert_allclose(bag.poses, folder.poses, atol=1e-9)
    np.testing.assert_array_equal(bag.pose_stream[0], gt.stamps_ns[rows] / 1e9)
    np.testing.assert_allclose(bag.pose_stream[1], gt.poses[rows], atol=1e-9)
    # The span follows the frames written: two frames, 100.0 and 100.1 s.
    tum_to_rosbag(src, tmp_path / 'two', max_frames=2, show_progress=False)
    rows = _rows_in_span(gt.stamps_ns, 100_000_000_000, 100_100_000_000)
    assert gt.stamps_ns[rows][[0, -1]].tolist() == [99_500_000_000, 100_600_000_000]
    _check_own_samples(tmp_path / 'two', gt.stamps_ns[rows], gt.poses[rows])


def test_existing_output_and_overwrite(tmp_path):
    src = tmp_path / 'tum'
    make_tum_folder(src, n=3)
    out = tmp_path / 'bag'
    tum_to_rosbag(src, out, max_frames=1, show_progress=False)
    with pytest.raises(ValueError, match='already exists'):
        tum_to_rosbag(src, out, show_progress=False)
    result = tum_to_rosbag(src, out, overwrite=True, storage='sqlite3', show_progress=False)
    assert result.frames == 3 and bag_topics(out)[RGB] == ('sensor_msgs/msg/Image', 3)
    not_a_bag = tmp_path / 'precious'
    not_a_bag.mkdir()
    (not_a_bag / 'notes.txt').write_text('keep me')
    with pytest.raises(ValueError, match='not a rosbag2 folder: refusing'):
        tum_to_rosbag(src, not_a_bag, overwrite=True, show_progress=False)
    assert (not_a_bag / 'notes.txt').read_text() == 'keep me'

    # A bag recorded elsewhere (a robot's ros2 bag record: no mark of ours) is never replaced,
    # --overwrite or not: a recording cannot be made again.
    from rosbags.rosbag2 import Writer

    recording = tmp_path / 'robot_recording'
    with Writer(recording, version=9) as foreign:
        foreign.add_connection('/chatter', 'std_msgs/msg/String', typestore=bag_typestore())
    before = (recording / 'metadata.yaml').read_text()
    with pytest.raises(
        ValueError,
        match=r"without depth-fusion's mark .* a recording or a bag converted before the mark .*: refusing",
    ):
        tum_to_rosbag(src, recording, overwrite=True, show_progress=False)
    assert (recording / 'metadata.yaml').read_text() == before
    assert 'written_by: depth_fusion_ros' in (out / 'metadata.yaml').read_text()  # ours carry it


def test_interrupted_conversion_leaves_no_bag(tmp_path, monkeypatch):
    src = tmp_path / 'tum'
    make_tum_folder(src, n=6)
    calls = {'n': 0}
    real = tum_to_bag.read_rgb_file

    def flaky(path, camera=None):
        calls['n'] += 1
        if calls['n'] == 4:
            raise KeyboardInterrupt
        return real(path, camera)

    monkeypatch.setattr(tum_to_bag, 'read_rgb_file', flaky)
    with pytest.raises(KeyboardInterrupt):
        tum_to_rosbag(src, tmp_path / 'bag', show_progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['tum']


def test_cli_convert(tmp_path, capsys):
    src = tmp_path / 'tum'
    make_tum_folder(src, n=3)
    out = tmp_path / 'out.db'
    assert (
        cli_main(['convert', str(src), str(out), '--storage', 'sqlite3', '--frames', '2', '--no-progress'])
        == 0
    )
    printed = capsys.readouterr().out
    assert 'wrote' in printed and 'poses from groundtruth.txt, its own samples' in printed
    gt = read_groundtruth(src / 'groundtruth.txt').stamps_ns
    written = load_bag_sequence(out, width=32, height=24).stamps
    rows = _rows_in_span(gt, round(written[0] * 1e9), round(written[-1] * 1e9))
    assert len(written) == 2 and bag_topics(out)[POSE] == ('geometry_msgs/msg/PoseStamped', int(rows.sum()))
    assert cli_main(['convert', str(src), str(out), '--no-progress']) == 1
    assert 'already exists (pass --overwrite' in capsys.readouterr().err
    assert cli_main(['convert', str(src), str(tmp_path / 'x'), '--groundtruth', 'g.txt']) == 1
    assert 'only apply to a ROS 1 bag' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(['convert', '--help'])
    assert 'TUM RGB-D folder' in capsys.readouterr().out


# --------------------------------------------------------------------------- ROS 1 bags

ROS1 = get_typestore(Stores.ROS1_NOETIC)
# Noetic's built-in store lacks tf2_msgs; real TUM bags carry its definition in the bag.
ROS1.register(get_types_from_msg('geometry_msgs/TransformStamped[] transforms', 'tf2_msgs/msg/TFMessage'))
CAM = PinholeCamera(64, 48, 50.0, 52.0, 31.5, 23.5)
T_KINECT_OPTICAL = make_pose([0.02, -0.01, 0.03], [-0.5, 0.5, -0.5, 0.5])


def _T_world_kinect(t: float) -> np.ndarray:
    return make_pose([0.5 * (t - 99.95), 0.2, 1.0], [0.0, 0.0, 0.2588190, 0.9659258])


def _transform_stamped(parent: str, child: str, t_ns: int, T: np.ndarray, kind=ROS1):
    k = m.as_kind(kind)
    tr, q = T[:3, 3], m.pose_msg(T, kind=k).orientation
    transform = k.new(
        'geometry_msgs/msg/Transform',
        translation=k.new('geometry_msgs/msg/Vector3', x=tr[0], y=tr[1], z=tr[2]),
        rotation=q,
    )
    return k.new(
        'geometry_msgs/msg/TransformStamped',
        header=m.header_msg(t_ns, parent, kind=k),
        child_frame_id=child,
        transform=transform,
    )


def _tf_msg(parent: str, child: str, t_ns: int, T: np.ndarray):
    stamped = _transform_stamped(parent, child, t_ns, T)
    return m.as_kind(ROS1).new('tf2_msgs/msg/TFMessage', transforms=[stamped])


def _pose_topic_msg(msgtype: str, T: np.ndarray, t_ns: int):
    """``T`` as a ROS 1 message of one of the pose types a pose topic may carry."""
    k = m.as_kind(ROS1)
    hdr = m.header_msg(t_ns, '/world', kind=ROS1)
    if msgtype == 'geometry_msgs/msg/PoseStamped':
        return m.pose_stamped_msg(T, hdr, kind=ROS1)
    if msgtype == 'geometry_msgs/msg/TransformStamped':
        return _transform_stamped('/world', '/openni_rgb_optical_frame', t_ns, T)
    pose = m.pose_msg(T, kind=k)
    with_cov = k.new('geometry_msgs/msg/PoseWithCovariance', pose=pose, covariance=np.zeros(36))
    if msgtype == 'geometry_msgs/msg/PoseWithCovarianceStamped':
        return k.new(msgtype, header=hdr, pose=with_cov)
    return odometry_msg(T, hdr, '/openni_rgb_optical_frame', kind=ROS1)


def pose_topic_samples(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A PoseStamped source at 100 Hz on its own stamps (3 ms off the images), from 1 s before the
    first image to about 1 s after the last one of ``n``."""
    stamps = 98_953_000_000 + 10_000_000 * np.arange(n * 10 + 200, dtype=np.int64)
    return stamps, np.stack([_T_world_kinect(t / 1e9) @ T_KINECT_OPTICAL for t in stamps.tolist()])


def write_ros1_bag(path: Path, n: int = 5, tf: bool = True, pose_topic: bool | str = False) -> dict:
    """A TUM-like ROS 1 bag: bgr8 colour at 10 Hz, 16UC1 depth 5 ms later, tf at 100 Hz; with
    ``pose_topic`` the optical frame's poses on /camera/pose too (``pose_topic_samples``), as
    PoseStamped or as the message type ``pose_topic`` names."""
    rng = np.random.default_rng(1)
    events: list[tuple[int, str, str, object]] = []
    truth = {}
    calib = CameraCalibration(CAM, 'plumb_bob', DISTORTION)
    for i in range(n):
        t_ns = 100_000_000_000 + i * 100_000_000
        rgb = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
        mm = rng.integers(0, 6000, (48, 64)).astype(np.uint16)
        hdr = m.header_msg(t_ns, '/openni_rgb_optical_frame', kind=ROS1)
        events.append(
            (t_ns, RGB, 'sensor_msgs/msg/Image', m.image_msg(rgb[..., ::-1].copy(), 'bgr8', hdr, kind=ROS1))
        )
        events.append((t_ns, INFO, 'sensor_msgs/msg/CameraInfo', m.camera_info_msg(calib, hdr, kind=ROS1)))
        d_ns = t_ns + 5_000_000
        dhdr = m.header_msg(d_ns, '/openni_depth_optical_frame', kind=ROS1)
        events.append((d_ns, DEPTH, 'sensor_msgs/msg/Image', m.image_msg(mm, '16UC1', dhdr, kind=ROS1)))
        truth[t_ns] = {'rgb': rgb, 'depth_mm': mm, 'pose': _T_world_kinect(t_ns / 1e9) @ T_KINECT_OPTICAL}
    if tf:
        for j in range(int(n * 10 + 10)):
            t_ns = 99_950_000_000 + j * 10_000_000
            msg = _tf_msg('/world', '/kinect', t_ns, _T_world_kinect(t_ns / 1e9))
            events.append((t_ns, '/tf', 'tf2_msgs/msg/TFMessage', msg))
            if j % 10 == 0:  # ROS 1 style: a fixed transform republished on /tf
                msg = _tf_msg('/kinect', '/openni_rgb_optical_frame', t_ns, T_KINECT_OPTICAL)
                events.append((t_ns, '/tf', 'tf2_msgs/msg/TFMessage', msg))
    if pose_topic:
        msgtype = pose_topic if isinstance(pose_topic, str) else 'geometry_msgs/msg/PoseStamped'
        for t_ns, T in zip(*pose_topic_samples(n), strict=True):
            events.append((int(t_ns), POSE, msgtype, _pose_topic_msg(msgtype, T, int(t_ns))))
    events.sort(key=lambda e: e[0])
    with Ros1Writer(path) as writer:
        conns = {}
        for t_ns, topic, msgtype, msg in events:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ROS1)
            writer.write(conns[topic], t_ns, ROS1.serialize_ros1(msg, msgtype))
    return truth


def _check_ros1_output(out: Path, truth: dict, n: int) -> None:
    """One pose per colour frame (a /tf chain), and the images."""
    stamps, poses = read_poses(out)
    assert stamps.tolist() == sorted(truth)[:n]
    for stamp, T in zip(stamps.tolist(), poses, strict=True):
        np.testing.assert_allclose(T, truth[stamp]['pose'], atol=1e-9)
    _check_ros1_images(out, truth, n)


def _check_ros1_images(out: Path, truth: dict, n: int) -> None:
    depth = read_depth_images(out, DEPTH)  # re-stamped with the colour stamps
    assert sorted(depth) == sorted(truth)[:n]
    for stamp, d in depth.items():
        mm = truth[stamp]['depth_mm']
        np.testing.assert_array_equal(np.isnan(d), mm == 0)
        np.testing.assert_allclose(d[mm > 0], mm[mm > 0] / 1000.0, rtol=1e-6)
    for _, bag_time, msg in iter_messages(out, [RGB]):
        assert msg.encoding == 'rgb8' and m.stamp_to_ns(msg.header.stamp) == bag_time
        np.testing.assert_array_equal(m.image_to_rgb(msg), truth[bag_time]['rgb'])


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_ros1_bag_with_tf_poses(tmp_path, storage):
    src = tmp_path / 'tum.bag'
    truth = write_ros1_bag(src)
    out = tmp_path / 'ros2'
    result = recorded_to_rosbag2(src, out, storage=storage, show_progress=False)
    assert result.frames == 5 and result.pose_source.startswith('/tf (world -> openni_rgb_optical_frame)')
    assert result.pose_source.endswith('interpolated at the colour stamps')  # a chain: at common stamps
    assert result.messages == {RGB: 5, INFO: 5, DEPTH: 5, POSE: 5}
    _check_ros1_output(out, truth, 5)
    seq = load_bag_sequence(out, width=32, height=24)
    assert len(seq) == 5 and seq.gt_camera == CAM
    np.testing.assert_allclose(seq.frames[2].pose, truth[sorted(truth)[2]]['pose'], atol=1e-9)


def test_ros1_bag_with_groundtruth_and_camera_yaml(tmp_path):
    src = tmp_path / 'tum.bag'
    truth = write_ros1_bag(src, n=4, tf=False)
    gt = tmp_path / 'groundtruth.txt'
    lines = ['# timestamp tx ty tz qx qy qz qw']
    for stamp in sorted(truth):
        T = truth[stamp]['pose']
        t, q = T[:3, 3], m.pose_msg(T, kind=ROS1).orientation
        values = ' '.join(repr(float(v)) for v in (*t, q.x, q.y, q.z, q.w))
        lines.append(f'{stamp / 1e9:.9f} {values}')
    gt.write_text('\n'.join(lines) + '\n')
    yaml_cam = PinholeCamera(64, 48, 60.0, 61.0, 32.0, 24.0)
    write_camera_yaml(tmp_path / 'camera.yaml', yaml_cam, (0.1, 0, 0, 0, 0))
    out = tmp_path / 'ros2'
    result = convert(
        src, out, groundtruth=gt, camera_yaml=tmp_path / 'camera.yaml', max_frames=3, show_progress=False
    )
    assert result.frames == 3 and result.pose_source.startswith('groundtruth')
    assert result.pose_source.endswith('its own samples')
    # The file's rows (all 4: the last is the first at or after the last frame + 0.5 s), not 3.
    stamps = np.asarray(sorted(truth), dtype=np.int64)
    _check_own_samples(out, stamps, np.stack([truth[s]['pose'] for s in stamps.tolist()]))
    _check_ros1_images(out, truth, 3)
    for _, _, info in iter_messages(out, [INFO]):
        assert m.camera_info_to_calibration(info).camera == yaml_cam


@pytest.mark.parametrize(
    'msgtype',
    [
        'geometry_msgs/msg/PoseStamped',
        'geometry_msgs/msg/PoseWithCovarianceStamped',
        'nav_msgs/msg/Odometry',
        'geometry_msgs/msg/TransformStamped',
    ],
)
def test_ros1_bag_with_a_pose_topic_keeps_its_own_samples(tmp_path, msgtype):
    """A pose topic at 100 Hz, 3 ms off the images: the bag carries its samples from the last at
    or before the first frame - 0.5 s to the first at or after the last frame + 0.5 s. Any of the
    pose types the nodes read (a motion-capture bridge's TransformStamped, an odometry) is read."""
    src = tmp_path / 'tum.bag'
    truth = write_ros1_bag(src, tf=False, pose_topic=msgtype)
    out = tmp_path / 'ros2'
    result = recorded_to_rosbag2(src, out, show_progress=False)
    assert result.frames == 5 and result.pose_source == 'pose topic, its own samples'
    stamps, poses = pose_topic_samples(5)
    rows = _rows_in_span(stamps, min(truth), max(truth))
    assert stamps[rows][[0, -1]].tolist() == [99_493_000_000, 100_903_000_000] and rows.sum() < len(stamps)
    assert result.messages == {RGB: 5, INFO: 5, DEPTH: 5, POSE: int(rows.sum())}
    _check_own_samples(out, stamps[rows], poses[rows])
    _check_ros1_images(out, truth, 5)
    seq = load_bag_sequence(out, width=32, height=24)
    assert seq.stamps.tolist() == [s / 1e9 for s in sorted(truth)]
    for f in seq.frames:  # read at the images, the poses there
        np.testing.assert_allclose(f.pose, truth[round(f.stamp * 1e9)]['pose'], atol=1e-9)


def test_ros1_bag_errors(tmp_path):
    src = tmp_path / 'tum.bag'
    write_ros1_bag(src, n=2, tf=False)
    result = recorded_to_rosbag2(src, tmp_path / 'noposes', show_progress=False)
    assert result.pose_source == 'none' and POSE not in result.messages and result.frames == 2
    with pytest.raises(ValueError, match=r'no colour topic /camera/rgb/image_raw \(it has:'):
        recorded_to_rosbag2(
            src, tmp_path / 'x', source_topics=BagTopics(rgb='/camera/rgb/image_raw'), show_progress=False
        )
    with pytest.raises(FileNotFoundError, match=r'missing\.bag'):
        convert(tmp_path / 'missing.bag', tmp_path / 'y')
    tree = TfTree()
    tree.add('/world', '/kinect', 1, np.eye(4))
    with pytest.raises(ValueError, match="no /tf chain from 'world' to 'camera'"):
        tree.lookup('world', 'camera', np.array([1]))


# --------------------------------------------------------------------------- a robot's rosbag2

JAZZY = get_typestore(Stores.ROS2_JAZZY)
ROBOT_RGB, ROBOT_INFO = '/cam/color/image_raw', '/cam/color/camera_info'
ROBOT_DEPTH = '/cam/aligned_depth_to_color/image_raw'


def write_robot_rosbag2(path: Path, n: int = 5) -> dict:
    """What a robot's ``ros2 bag record`` holds, in ``write_ros1_bag``'s scene: PNG colour on
    ``<image>/compressed`` (image_transport), 16UC1 depth 5 ms later, the body's odometry frame
    on ``/tf`` at 100 Hz and the camera's mount once on ``/tf_static``; no pose topic."""
    rng = np.random.default_rng(1)
    calib = CameraCalibration(CAM, 'plumb_bob', DISTORTION)
    events: list[tuple[int, str, str, object]] = []
    truth = {}
    for i in range(n):
        t_ns = 100_000_000_000 + i * 100_000_000
        rgb = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
        mm = rng.integers(0, 6000, (48, 64)).astype(np.uint16)
        hdr = m.header_msg(t_ns, 'cam_color_optical_frame', kind=JAZZY)
        compressed = compressed_image_msg(rgb, hdr, kind=JAZZY, fmt='png')
        events.append((t_ns, ROBOT_RGB + '/compressed', 'sensor_msgs/msg/CompressedImage', compressed))
        events.append(
            (t_ns, ROBOT_INFO, 'sensor_msgs/msg/CameraInfo', m.camera_info_msg(calib, hdr, kind=JAZZY))
        )
        d_ns = t_ns + 5_000_000
        dhdr = m.header_msg(d_ns, 'cam_color_optical_frame', kind=JAZZY)
        events.append(
            (d_ns, ROBOT_DEPTH, 'sensor_msgs/msg/Image', m.image_msg(mm, '16UC1', dhdr, kind=JAZZY))
        )
        truth[t_ns] = {'rgb': rgb, 'depth_mm': mm, 'pose': _T_world_kinect(t_ns / 1e9) @ T_KINECT_OPTICAL}
    tf = 'tf2_msgs/msg/TFMessage'
    mount = _transform_stamped(
        'base_link', 'cam_color_optical_frame', 99_950_000_000, T_KINECT_OPTICAL, JAZZY
    )
    events.append((99_950_000_000, '/tf_static', tf, JAZZY.types[tf](transforms=[mount])))
    for j in range(int(n * 10 + 10)):
        t_ns = 99_950_000_000 + j * 10_000_000
        odom = _transform_stamped('odom', 'base_link', t_ns, _T_world_kinect(t_ns / 1e9), JAZZY)
        events.append((t_ns, '/tf', tf, JAZZY.types[tf](transforms=[odom])))
    events.sort(key=lambda e: e[0])
    with AtomicBagWriter(path) as writer:
        for t_ns, topic, msgtype, msg in events:
            writer.write(topic, msgtype, t_ns, msg)
    return truth


def test_a_robots_rosbag2_with_tf_poses_and_compressed_colour(tmp_path, capsys):
    """A robot's own recording converts into the layout the nodes read: its topic names given,
    the compressed colour found on ``<image>/compressed``, 16UC1 depth in metres re-stamped
    with its colour frame, and the poses of the /tf chain odom -> base_link -> camera (the
    mount from /tf_static) at the colour stamps, read back as a sequence."""
    src = tmp_path / 'robot'
    truth = write_robot_rosbag2(src)
    out = tmp_path / 'ros2'
    args = [
        'convert',
        str(src),
        str(out),
        '--src-rgb-topic',
        ROBOT_RGB,
        '--src-camera-info-topic',
        ROBOT_INFO,
    ]
    args += ['--src-depth-topic', ROBOT_DEPTH, '--tf-world-frame', 'odom', '--no-progress']
    assert cli_main(args) == 0
    printed = capsys.readouterr().out
    assert 'poses from /tf (odom -> cam_color_optical_frame)' in printed, printed
    _check_ros1_output(out, truth, 5)
    seq = load_bag_sequence(out, width=32, height=24)
    assert len(seq) == 5 and seq.gt_camera == CAM
    assert cli_main(['convert', str(src), str(tmp_path / 'x'), '--no-progress']) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'no colour topic /camera/rgb/image_color (it has:' in err, err
    assert f'{ROBOT_RGB}/compressed' in err


def test_a_rosbag2_cut_short_is_sent_to_repair(tmp_path, capsys):
    """A recording folder with its storage file but no metadata.yaml (the recorder was killed) is
    not converted as it is: the one-line error sends it to ``--repair``."""
    src = tmp_path / 'robot'
    write_robot_rosbag2(src, n=2)
    (src / 'metadata.yaml').unlink()
    assert cli_main(['convert', str(src), str(tmp_path / 'out'), '--no-progress']) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'convert --repair it first' in err, err


def test_tum_fr1_xyz_converts(tum_fr1_xyz, tmp_path):
    out = tmp_path / 'fr1'
    result = tum_to_rosbag(tum_fr1_xyz, out, max_frames=3, show_progress=False)
    assert result.frames == 3
    bag = load_bag_sequence(out)
    folder = load_tum_sequence(tum_fr1_xyz, max_frames=3)
    for a, b in zip(folder.frames, bag.frames, strict=True):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-9)
