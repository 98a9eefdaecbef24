"""multi_view_node over real DDS: poses from a separate stream, keyframes, accuracy, bad inputs.

The accuracy test compares the node with the paper's sweep run offline, so it pins
``multi_view.method: sweep`` (the default is the filter: test_nodes_multi_view_filter.py).
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, TimeReference
from std_msgs.msg import String

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.geometry import interpolate_poses
from depth_fusion_ros.multiview.neighbours import NeighbourConfig, select_neighbours
from depth_fusion_ros.multiview.semidense import MultiViewConfig, estimate_semidense
from depth_fusion_ros.nodes.multi_view_node import MultiViewNode
from depth_fusion_ros.nodes.qos import latched_qos, qos_profile
from depth_fusion_ros.nodes.testing import RosHarness

K = m.RCLPY
FRAME = 'camera_rgb_optical_frame'


def _mv_node(ros: RosHarness, **params) -> MultiViewNode:
    """A multi_view_node in ``ros`` with these parameter overrides (dotted names as keywords:
    ``**{'filter.max_lag_frames': 0}``). The calibration checks' process runs at the node's
    priority unless asked otherwise: a test that waits for a check's verdict would otherwise wait
    on a niced process that the other test worker starves (test_check_process.py checks the
    niceness)."""
    params = {'calibration_checks.nice': 0, **params}
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return ros.add(MultiViewNode(context=ros.context, parameter_overrides=overrides))


def _stream_check_node(ros: RosHarness, size: dict, **params) -> MultiViewNode:
    """A multi_view_node for the calibration checks' streams: a keyframe every 6th frame, deep
    queues, the filter on every frame without lag, on ``size``'s working grid."""
    filter_params = {'filter.max_lag_frames': 0, 'filter.max_update_rate': 0.0}
    return _mv_node(
        ros,
        keyframe_every=6,
        queue_size=16,
        qos_depth=100,
        width=size['width'],
        height=size['height'],
        **filter_params,
        **params,
    )


def _checks_caught_up(ros: RosHarness, node: MultiViewNode, posed: int, timeout: float = 60.0) -> None:
    """Waits until ``node`` has posed ``posed`` frames and its calibration checks' threads have
    taken every frame queued for them. A test that waits so before each next frame feeds its
    checks the samples an idle machine would: on a loaded one (two test workers on two cores) a
    busy check thread drops frames by design, and its samples move (CI once saw 11 of 12 focal
    check pairs at the frame a test waited at)."""
    checks = (node.focal_check, node.time_offset_check, node.mount_check)
    done = ros.wait_for(lambda: node.posed_count >= posed and not any(c.pending for c in checks), timeout)
    assert done, (node.posed_count, posed, [c.pending for c in checks])


def _send_checked(
    ros: RosHarness, node: MultiViewNode, cam: _Camera, pose_stamp: tuple, image: tuple, posed: int
) -> None:
    """One frame of a calibration check's stream: its pose ``(T_wc, stamp_ns)`` and image
    ``(rgb, stamp_ns, camera)``, then the wait until ``posed`` frames are posed and the checks
    have taken theirs (``_checks_caught_up``)."""
    cam.publish_pose(*pose_stamp)
    cam.publish_image(*image)
    time.sleep(0.03)
    _checks_caught_up(ros, node, posed)


def _wait_keyframes_out(ros: RosHarness, node: MultiViewNode, depths: list, frames: int) -> None:
    """Waits until ``node`` has posed ``frames`` frames and published a depth for every keyframe
    it chose."""
    done = ros.wait_for(lambda: node.posed_count == frames and len(depths) == node.keyframes_decided, 120.0)
    assert done, node.stats.snapshot().summary()


def _notes_of(node: MultiViewNode) -> list[tuple[str, str]]:
    """Every note ``node`` counts from now on, ``(reason, message)``, as it counts it: the
    throttled log says a repeated note once, the test needs its text."""
    notes: list[tuple[str, str]] = []
    noted = node.stats.noted

    def noting(reason: str, message: str = '', count: int = 1) -> None:
        notes.append((reason, message))
        noted(reason, message, count)

    node.stats.noted = noting
    return notes


class _Camera:
    """Publishers of what a camera driver and a SLAM system publish."""

    def __init__(self, ros: RosHarness) -> None:
        deep = qos_profile('reliable', 100)  # a slow subscriber must not lose a burst
        self.image = ros.publisher(Image, '/camera/rgb/image_color', deep)
        self.info = ros.publisher(CameraInfo, '/camera/rgb/camera_info', deep)
        self.pose = ros.publisher(PoseStamped, '/camera/pose', deep)
        self.poses_published = 0
        assert ros.wait_for_subscribers([self.image, self.info, self.pose])

    def publish_image(self, rgb: np.ndarray, stamp_ns: int, camera, encoding: str = 'rgb8') -> None:
        header = m.header_msg(stamp_ns, FRAME, kind=K)
        self.info.publish(m.camera_info_msg(camera, header, kind=K))
        msg = m.rgb_image_msg(rgb, header, kind=K)
        msg.encoding = encoding
        self.image.publish(msg)

    def publish_pose(self, T_wc: np.ndarray, stamp_ns: int) -> None:
        self.poses_published += 1
        self.pose.publish(m.pose_stamped_msg(T_wc, m.header_msg(stamp_ns, 'world', kind=K), kind=K))


def _collect_outputs(ros: RosHarness) -> dict[str, list]:
    return {
        'depth': ros.collect(Image, '/depth_fusion/multi_view/depth'),
        'score': ros.collect(Image, '/depth_fusion/multi_view/score'),
        'keyframe': ros.collect(Image, '/depth_fusion/keyframe/image'),
        'keyframe_info': ros.collect(CameraInfo, '/depth_fusion/keyframe/camera_info'),
    }


def _stamps(messages: list) -> list[int]:
    return [m.stamp_to_ns(msg.header.stamp) for msg in messages]


def test_slam_rate_poses_are_interpolated_and_depth_is_accurate(synthetic_sequence, tmp_path):
    """Poses at 2.5x the image rate, at other stamps than the images (but the first), published
    after the image (as a SLAM system would); parameters from a --params-file that changes the
    keyframe stride and picks the sweep."""
    seq = synthetic_sequence
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    pose_stamps = np.concatenate(
        ([seq.stamps[0]], np.arange(seq.stamps[0] + 0.007, seq.stamps[-1], 1 / 75.0))
    )
    pose_T, valid = interpolate_poses(seq.stamps, seq.poses, pose_stamps)
    assert valid.all()
    params = tmp_path / 'params.yaml'
    params.write_text(
        'multi_view_node:\n  ros__parameters:\n    keyframe_every: 6\n    queue_size: 8\n    qos_depth: 100\n'
        "    multi_view.method: 'sweep'\n"
    )

    with RosHarness(args=['--ros-args', '--params-file', str(params)]) as ros:
        node = ros.add(MultiViewNode(context=ros.context))
        assert node.params['keyframe_every'] == 6  # the default is 5
        assert node.filter_feed is None  # the sweep, from the file (the default is the filter)
        out = _collect_outputs(ros)
        methods = ros.collect(String, '/depth_fusion/multi_view/method', latched_qos())
        biases = ros.collect(Image, '/depth_fusion/multi_view/bias_std')  # the filter's only
        cam = _Camera(ros)
        first_pose = 0
        for i, frame in enumerate(seq.frames):
            cam.publish_image(frame.rgb, stamps[i], seq.camera)
            # the SLAM answers a little later with the poses up to just after this image
            horizon = seq.stamps[i] + 0.014 if i + 1 < len(seq.frames) else np.inf
            while first_pose < len(pose_stamps) and pose_stamps[first_pose] <= horizon:
                cam.publish_pose(pose_T[first_pose], m.sec_to_ns(float(pose_stamps[first_pose])))
                first_pose += 1
            time.sleep(0.02)
        # the last images lie after the last pose stamp: only a pose at or after them covers them
        cam.publish_pose(seq.poses[-1], stamps[-1])
        expected_keys = [6, 12, 18]  # posed frames 0, 6, 12 ... with at least one past neighbour
        # the third keyframe can come out before the final pose lands: wait for both
        assert ros.wait_for(
            lambda: len(out['score']) == len(expected_keys) and node.posed_count == len(seq.frames),
            120.0,
        ), node.stats.snapshot().summary()
        snap = node.stats.snapshot()

    assert snap.dropped == {}, snap.summary()
    assert {msg.data for msg in methods} == {'sweep'}  # fusion_node's stage 1 follows it (announce.py)
    assert biases == [] and node._bias_pub is None  # the sweep has no focal bias to send
    assert snap.received['pose'] == cam.poses_published and node.posed_count == len(seq.frames)
    key_stamps = [stamps[k] for k in expected_keys]
    for name in ('depth', 'score', 'keyframe', 'keyframe_info'):
        assert _stamps(out[name]) == key_stamps, name
        assert all(msg.header.frame_id == FRAME for msg in out[name])
    for k, kf, info in zip(expected_keys, out['keyframe'], out['keyframe_info'], strict=True):
        np.testing.assert_array_equal(m.image_to_rgb(kf), seq.frames[k].rgb)  # undistorted already, same size
        assert info.k[0] == pytest.approx(seq.camera.fx) and list(info.d) == [0.0] * 5

    published_stamps = np.append(pose_stamps, seq.stamps[-1])
    node_poses, _ = interpolate_poses(published_stamps, np.concatenate((pose_T, seq.poses[-1:])), seq.stamps)
    rel_errors = []
    for k, depth_msg, score_msg in zip(expected_keys, out['depth'], out['score'], strict=True):
        depth = m.image_to_numpy(depth_msg)
        score = m.image_to_numpy(score_msg)
        gt = seq.frames[k].depth
        valid = np.isfinite(depth) & np.isfinite(gt)
        assert valid.mean() > 0.05, f'keyframe {k}: density {valid.mean():.3f}'
        assert np.array_equal(np.isfinite(score), np.isfinite(depth))
        rel = np.abs(depth[valid] - gt[valid]) / gt[valid]
        rel_errors.append(np.median(rel))
        # The same search offline, on the poses the node could know (the pose stream interpolated
        # at the image stamps) and the same online neighbours: the node adds nothing of its own.
        neighbours = select_neighbours(node_poses[: k + 1], k, 4, 'online', seq.camera, NeighbourConfig())
        offline = estimate_semidense(
            seq.frames[k].gray,
            node_poses[k],
            [seq.frames[i].gray for i in neighbours],
            [node_poses[i] for i in neighbours],
            seq.camera,
            MultiViewConfig(),
        ).depth
        both = np.isfinite(depth) & np.isfinite(offline)
        assert both.sum() > 0.99 * np.isfinite(offline).sum()
        assert np.median(np.abs(depth[both] - offline[both]) / offline[both]) < 1e-4
    assert max(rel_errors) < 0.04, rel_errors


def test_bad_inputs_are_dropped_counted_and_processing_goes_on(synthetic_sequence):
    seq = synthetic_sequence
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    with RosHarness() as ros:
        node = ros.add(
            MultiViewNode(
                context=ros.context,
                parameter_overrides=[
                    Parameter('width', value=160),
                    Parameter('height', value=120),
                    Parameter('keyframe_every', value=3),
                    Parameter('max_pose_gap', value=0.1),
                    Parameter('queue_size', value=10),
                    # the stream below comes every 10 ms: a loaded machine's executor must not
                    # lose images in a 10-deep reader history (CI: 26 of 28 received once)
                    Parameter('qos_depth', value=100),
                    # drop at once (the default waits for a late camera_info: test_graph_pacing)
                    Parameter('camera_info_wait', value=0.0),
                    Parameter('filter.max_lag_frames', value=0),  # every frame: its density is checked
                    Parameter('filter.max_update_rate', value=0.0),
                ],
            )
        )
        out = _collect_outputs(ros)
        cam = _Camera(ros)

        def expect(reason: str, count: int = 1) -> None:
            ok = ros.wait_for(lambda: node.stats.snapshot().dropped.get(reason, 0) == count, 10.0)
            assert ok, f'{reason}: {node.stats.snapshot().summary()}'

        rgb = seq.frames[0].rgb
        cam.image.publish(m.rgb_image_msg(rgb, m.header_msg(stamps[0], FRAME, kind=K), kind=K))
        expect('no_camera_info')
        uncalibrated = m.camera_info_msg(seq.camera, m.header_msg(stamps[0], FRAME, kind=K), kind=K)
        uncalibrated.k = [0.0] * 9
        cam.info.publish(uncalibrated)
        expect('bad_camera_info')
        cam.publish_image(rgb, stamps[0], seq.camera, encoding='yuv420')
        expect('bad_encoding')
        small = np.ascontiguousarray(rgb[::2, ::2])
        cam.image.publish(m.rgb_image_msg(small, m.header_msg(stamps[0], FRAME, kind=K), kind=K))
        expect('size_mismatch')
        cam.publish_image(seq.frames[1].rgb, stamps[1], seq.camera)  # waits for a pose ...
        cam.publish_image(seq.frames[1].rgb, stamps[1], seq.camera)
        expect('duplicate_stamp_image')
        cam.publish_image(rgb, stamps[0], seq.camera)
        expect('stamp_out_of_order_image')
        broken = m.pose_stamped_msg(seq.poses[2], m.header_msg(stamps[2], 'world', kind=K), kind=K)
        broken.pose.orientation.x = float('nan')
        cam.pose.publish(broken)
        broken.pose.orientation.x, broken.pose.orientation.w = 0.3, 1.2  # |q| != 1
        cam.pose.publish(broken)
        expect('bad_pose', 2)
        cam.publish_pose(seq.poses[2], stamps[2])  # ... and the first pose comes after frame 1
        expect('no_pose')
        cam.publish_pose(seq.poses[2], stamps[2])
        expect('duplicate_stamp_pose')
        cam.publish_pose(seq.poses[1], stamps[1])
        expect('stamp_out_of_order_pose')

        lost = range(11, 18)  # tracking lost: no poses for these frames (a 0.27 s gap)
        for i in range(2, len(seq.frames)):
            cam.publish_image(seq.frames[i].rgb, stamps[i], seq.camera)
            if i not in lost and i > 2:
                cam.publish_pose(seq.poses[i], stamps[i])
            time.sleep(0.01)
        expect('pose_gap', len(lost))
        # posed frames 2..10 and 18..23; keyframes every 3rd posed frame with a past neighbour
        before_gap, after_gap = [5, 8], [18, 21]
        assert ros.wait_for(lambda: len(out['score']) == 4, 120.0), node.stats.snapshot().summary()
        snap = node.stats.snapshot()

    assert snap.dropped == {
        'no_camera_info': 1,
        'bad_camera_info': 1,
        'bad_encoding': 1,
        'size_mismatch': 1,
        'duplicate_stamp_image': 1,
        'stamp_out_of_order_image': 1,
        'bad_pose': 2,
        'no_pose': 1,
        'duplicate_stamp_pose': 1,
        'stamp_out_of_order_pose': 1,
        'pose_gap': len(lost),
    }, snap.summary()
    assert _stamps(out['depth']) == [stamps[k] for k in before_gap + after_gap]
    for depth_msg in out['depth']:
        assert (depth_msg.width, depth_msg.height) == (160, 120)
        assert np.isfinite(m.image_to_numpy(depth_msg)).mean() > 0.02


def test_motion_keyframes_and_parameter_errors(synthetic_sequence):
    seq = synthetic_sequence
    with RosHarness() as ros:
        node = MultiViewNode(
            context=ros.context,
            parameter_overrides=[
                Parameter('keyframe_policy', value='motion'),
                Parameter('keyframe_min_translation', value=0.15),
            ],
        )
        keyframes = []
        for frame in seq.frames:  # what the node does for each posed frame
            if node._is_keyframe_candidate(frame):
                keyframes.append(frame.index)
                node._last_keyframe_pose = frame.pose
        node.destroy_node()
        assert keyframes[0] == 0 and len(keyframes) >= 3
        centres = seq.poses[keyframes, :3, 3]
        assert np.all(np.linalg.norm(np.diff(centres, axis=0), axis=1) >= 0.15)
        # every frame in between moved less than that since the keyframe before it
        for a, b in itertools.pairwise(keyframes):
            inside = seq.poses[a + 1 : b, :3, 3] - seq.poses[a, :3, 3]
            assert np.all(np.linalg.norm(inside, axis=1) < 0.15)
        with pytest.raises(ValueError, match='keyframe_policy'):
            MultiViewNode(
                context=ros.context, parameter_overrides=[Parameter('keyframe_policy', value='often')]
            )
        with pytest.raises(ValueError, match='min_depth < max_depth'):
            MultiViewNode(
                context=ros.context,
                parameter_overrides=[
                    Parameter('multi_view.min_depth', value=5.0),
                    Parameter('multi_view.max_depth', value=2.0),
                ],
            )


def test_images_waiting_for_poses_stay_bounded(synthetic_sequence):
    """An image stream without poses (SLAM not started): at most max_pending_images are kept."""
    seq = synthetic_sequence
    with RosHarness() as ros:
        node = _mv_node(ros, width=80, height=60, max_pending_images=5, pose_wait=100.0)
        cam = _Camera(ros)
        for i, frame in enumerate(seq.frames):
            cam.publish_image(frame.rgb, m.sec_to_ns(seq.stamps[i]), seq.camera)
        # a burst larger than the QoS history may lose some messages in transport: count arrivals
        received = ros.wait_until_stable(lambda: node.stats.snapshot().received.get('image', 0))
        snap = node.stats.snapshot()
        assert received > 5 and len(node.pending) == 5
    assert snap.dropped == {'pose_wait_overflow': received - 5}


def test_missing_images_are_counted_as_a_note(synthetic_sequence):
    """Images lost before the node's callback (the camera, the transport, or a subscription
    history overflowing) were counted nowhere: a gap of two and of three periods in the
    stamps is noted as 1 + 2 missing images, and the rest of the stream as none."""
    seq = synthetic_sequence
    skipped = {8, 14, 15}
    with RosHarness() as ros:
        node = _mv_node(ros, width=80, height=60, max_pending_images=30, pose_wait=100.0)
        cam = _Camera(ros)
        sent = [i for i in range(len(seq.frames)) if i not in skipped]
        for i in sent:
            cam.publish_image(seq.frames[i].rgb, m.sec_to_ns(seq.stamps[i]), seq.camera)
            time.sleep(0.01)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('image', 0) == len(sent), 20.0)
        snap = node.stats.snapshot()
    assert snap.noted.get('image_gap') == len(skipped), snap.summary()
    assert snap.dropped == {}, snap.summary()


def test_an_overflow_says_how_far_the_poses_are_behind(synthetic_sequence):
    """Poses that stall while images flow (a publisher of large raw images with Fast DDS
    defaults): the drop message gives the pose stream's lag and the usual cause."""
    seq = synthetic_sequence
    with RosHarness() as ros:
        node = _mv_node(ros, width=80, height=60, max_pending_images=3, pose_wait=100.0)
        cam = _Camera(ros)
        cam.publish_pose(seq.poses[0], m.sec_to_ns(seq.stamps[0]))
        assert ros.wait_for(lambda: node.pose_buffer.span is not None, 10.0)
        for i in range(1, 8):
            cam.publish_image(seq.frames[i].rgb, m.sec_to_ns(seq.stamps[i]), seq.camera)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('image', 0) == 7, 10.0)
        # an image that came just before its camera_info waits for it first (camera_info_wait)
        assert ros.wait_for(lambda: node.stats.snapshot().dropped.get('pose_wait_overflow', 0) == 4, 10.0)
        hint = node._pose_lag_hint()
    lag = seq.stamps[7] - seq.stamps[0]
    assert f'{lag:.1f} s behind the newest image' in hint and 'over UDP' in hint


def test_a_quiet_tick_waits_for_one_more_round_before_giving_up(synthetic_sequence):
    """End of stream (no input for pose_wait): the waiting images are dropped as no_pose, but
    only on a second tick with no input in between. On a loaded machine the executor serves
    the ready timer before a pose already queued for it; that pose must still land."""
    seq = synthetic_sequence
    with RosHarness() as ros:
        node = _mv_node(ros, width=80, height=60, pose_wait=100.0)  # its own timer never gives up here
        cam = _Camera(ros)
        cam.publish_image(seq.frames[0].rgb, m.sec_to_ns(seq.stamps[0]), seq.camera)
        assert ros.wait_for(lambda: len(node.pending) == 1, 10.0)
        node.params['pose_wait'] = 0.5
        node._last_input -= 1.0  # quiet for a second, as if the executor had been starved
        node._give_up_pending()
        assert len(node.pending) == 1  # first quiet tick: wait a round
        node._last_input = time.monotonic()  # an input came in between (the late pose)
        node._last_input -= 1.0
        node._give_up_pending()
        assert len(node.pending) == 1  # quiet again, but not across a whole round
        node._give_up_pending()  # a second tick with nothing in between: the end of the stream
        snap = node.stats.snapshot()
        assert len(node.pending) == 0
    assert snap.dropped == {'no_pose': 1}


def test_a_pose_time_offset_is_applied_before_the_pose_lookup(synthetic_sequence):
    """``pose_time_offset``: a pose source whose clock runs 20 ms ahead of the camera's stamps
    image ``i``'s pose at ``t_i + 0.02``; with the offset declared, every keyframe gets exactly
    that pose (not one interpolated between two frames), and the first image is posed
    although it is older than the first pose stamp."""
    seq = synthetic_sequence
    offset = 0.02
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    with RosHarness() as ros:
        node = _mv_node(ros, pose_time_offset=offset, queue_size=8, qos_depth=100)
        poses = ros.collect(PoseStamped, '/depth_fusion/keyframe/pose')
        times = ros.collect(TimeReference, '/depth_fusion/posing/pose_time', latched_qos())
        cam = _Camera(ros)
        for i, frame in enumerate(seq.frames):
            cam.publish_pose(frame.pose, stamps[i] + m.sec_to_ns(offset))
        for i, frame in enumerate(seq.frames):
            cam.publish_image(frame.rgb, stamps[i], seq.camera)
            time.sleep(0.01)
        assert ros.wait_for(lambda: node.posed_count == len(seq.frames) and len(poses) >= 2, 60.0), (
            node.stats.snapshot().summary()
        )
        snap = node.stats.snapshot()
    assert snap.dropped == {}, snap.summary()
    index = {s: i for i, s in enumerate(stamps)}
    for msg in poses:
        k = index[m.stamp_to_ns(msg.header.stamp)]  # stamped as its image, on the camera's clock
        np.testing.assert_allclose(m.pose_stamped_to_matrix(msg), seq.frames[k].pose, atol=1e-6)
    # Said to the nodes after it (nodes/posing.py), once: from the first image on, at +20 ms.
    assert len(times) == 1 and m.stamp_to_ns(times[0].header.stamp) == stamps[0], times
    assert m.stamp_to_ns(times[0].time_ref) == stamps[0] + m.sec_to_ns(offset)
