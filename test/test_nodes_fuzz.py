"""Every node under a barrage of malformed messages over real DDS (a seeded fuzzer).

What a robot sends a node by mistake is not the handful of cases the other node tests name:
a driver's odd encoding with a step that does not match, a camera_info with NaN in K and a
binning that does not divide its ROI, a depth image of negative infinities, a pose at 1e300 m.
Each must be a counted drop with a reason the node knows (an ``InputError`` or a graceful
fusion), never ``callback_error`` or ``processing_error`` (the guards' counters of something
nobody thought of, whose traceback only reaches the debug log), and the node must still turn
valid input into its output afterwards. The barrage is seeded: every run sends the same.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')

from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, TimeReference

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.qos import qos_profile
from depth_fusion_ros.nodes.testing import RosHarness

K = m.RCLPY
FRAME = 'camera_rgb_optical_frame'
#: the guards' counters of an unexpected exception: never allowed
UNEXPECTED = ('callback_error', 'processing_error')
#: the barrage's stamps lie before this; the valid input after it comes later
VALID_FROM_S = 1_900_000_000

ENCODINGS = (
    'rgb8', 'bgr8', 'rgba8', 'mono8', '8UC3', '8UC1', '32FC1', '16UC1', 'mono16', 'yuv422',
    'yuv422_yuy2', 'bayer_rggb8', 'bayer_gbrg16', 'rgb16', 'bgra16', 'nv21', '', 'RGB8', '64FC1',
)  # fmt: skip
#: bytes per pixel, to make steps that match (or are one off)
BYTES = {'rgb8': 3, 'bgr8': 3, '8UC3': 3, 'rgba8': 4, '32FC1': 4, '16UC1': 2, 'mono16': 2,
         'yuv422': 2, 'yuv422_yuy2': 2, 'bayer_gbrg16': 2, 'rgb16': 6, 'bgra16': 8, '64FC1': 8}  # fmt: skip
ODD_VALUES = (0.0, 1.0, -1.0, float('nan'), float('inf'), -float('inf'), 1e9, 1e-9, 131.25, 79.5)
FLOATS = np.array([np.nan, np.inf, -np.inf, -1.0, 0.0, 1e30, 2.5, 1e-30], np.float32)


class Fuzzer:
    """Malformed messages, half of them wholly random, half a valid one with one field broken
    (which reaches deeper: past the first check a random message fails)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self._clock_ns = 10**18  # 1e9 s: the barrage's stream, well before VALID_FROM_S

    def stamp_ns(self) -> int:
        """Mostly a stream's next stamp (30 Hz), so broken messages get past the stamp checks
        and into the pairing and the processing; one in ten anywhere in [0, 1.5e9) s."""
        if self.rng.random() < 0.1:
            return int(self.rng.integers(0, int(1.5e9))) * 10**9 + int(self.rng.integers(0, 10**9))
        self._clock_ns += 33_333_333
        return self._clock_ns

    def pick(self, options: Any) -> Any:
        return options[int(self.rng.integers(len(options)))]

    def header(self, frames: tuple[str, ...] = ('', FRAME, 'other')) -> Any:
        return m.header_msg(self.stamp_ns(), self.pick(frames), kind=K)

    def _payload(self, size: int) -> bytes:
        if self.rng.random() < 0.5:
            return self.rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        reps = -(-size // FLOATS.nbytes) if size else 0
        return np.tile(FLOATS, reps).tobytes()[:size]

    def image(self, valid: Callable[[], Any] | None = None) -> Any:
        """A broken Image: random, or ``valid()`` with its data, size, step or encoding broken."""
        if valid is not None and self.rng.random() < 0.5:
            msg = valid()
            how = self.pick(('values', 'encoding', 'step', 'truncate', 'size'))
            if how == 'values':  # NaN, inf, negative, huge where a depth or colour should be
                msg.data = self._payload(len(msg.data))
            elif how == 'encoding':
                msg.encoding = self.pick(ENCODINGS)
            elif how == 'step':
                msg.step = int(msg.step) + self.pick((-1, 1, 7))
            elif how == 'truncate':
                msg.data = bytes(msg.data)[: int(self.rng.integers(0, len(msg.data)))]
            else:
                msg.width, msg.height = self.pick(((0, 0), (1, 1), (msg.width // 2, msg.height)))
            msg.header = self.header((msg.header.frame_id,))
            return msg
        encoding = self.pick(ENCODINGS)
        width, height = self.pick((0, 1, 2, 3, 5, 160, 161)), self.pick((0, 1, 2, 120))
        row = width * BYTES.get(encoding, 1)
        step = max(0, row + self.pick((0, 0, 1, -1, 13)))
        size = min(step * height + self.pick((0, 0, -1, 7)), 1 << 20)
        msg = Image(header=self.header(), height=height, width=width, encoding=encoding, step=step)
        msg.is_bigendian = int(self.rng.integers(0, 2))
        msg.data = self._payload(max(size, 0))
        return msg

    def camera_info(self, valid: Callable[[], Any] | None = None) -> Any:
        msg = valid() if valid is not None else CameraInfo()
        msg.header = self.header((msg.header.frame_id or FRAME,))
        fields = ('k', 'd', 'p', 'model', 'size', 'binning', 'roi')
        broken = fields if valid is None or self.rng.random() < 0.3 else (self.pick(fields),)
        for name in broken:
            if name == 'k':
                msg.k = [float(self.pick(ODD_VALUES)) for _ in range(9)]
            elif name == 'p':
                msg.p = [float(self.pick(ODD_VALUES)) for _ in range(12)]
            elif name == 'd':
                msg.d = [float(self.pick(ODD_VALUES)) for _ in range(self.pick((0, 1, 4, 5, 8, 12, 14)))]
            elif name == 'model':
                msg.distortion_model = self.pick(('plumb_bob', 'rational_polynomial', 'equidistant', '', 'x'))
            elif name == 'size':
                msg.width, msg.height = self.pick((0, 1, 160, 320, 65535)), self.pick((0, 1, 120, 65535))
            elif name == 'binning':
                msg.binning_x, msg.binning_y = int(self.rng.integers(0, 5)), int(self.rng.integers(0, 5))
            else:
                roi = msg.roi
                roi.x_offset, roi.y_offset = self.pick((0, 1, 10, 1000)), self.pick((0, 1, 10, 1000))
                roi.width, roi.height = self.pick((0, 1, 80, 161, 5000)), self.pick((0, 1, 60, 5000))
        return msg

    def _broken_rotation(self, q: Any) -> None:
        q.x, q.y, q.z, q.w = self.pick(
            ((0.0, 0.0, 0.0, 0.0), (float('nan'), 0.0, 0.0, 1.0), (0.3, 0.0, 0.0, 1.2), (0.0, 0.0, 0.0, 1.0))
        )

    def _broken_position(self, p: Any) -> None:
        p.x, p.y, p.z = (
            float(self.pick((0.0, float('nan'), float('inf'), 1e300, -1e300, 1.0))) for _ in range(3)
        )

    def pose(self, T: np.ndarray | None = None, frames: tuple[str, ...] = ('', 'world', 'map')) -> Any:
        T = np.eye(4) if T is None else T
        msg = m.pose_stamped_msg(T, self.header(frames), kind=K)
        self._broken_position(msg.pose.position) if self.rng.random() < 0.5 else None
        self._broken_rotation(msg.pose.orientation) if self.rng.random() < 0.7 else None
        return msg

    def transform(self) -> Any:
        msg = TransformStamped(header=self.header(('', 'world')), child_frame_id=self.pick(('', FRAME, 'x')))
        self._broken_position(msg.transform.translation)
        self._broken_rotation(msg.transform.rotation)
        return msg

    def time_reference(self) -> Any:
        msg = TimeReference(header=self.header(), source=self.pick(('', 'pose', 'x' * 300)))
        msg.time_ref.sec = int(self.rng.integers(-(2**31), 2**31 - 1))
        msg.time_ref.nanosec = int(self.rng.integers(0, 2**32 - 1))
        return msg

    def path(self) -> Any:
        msg = PathMsg(header=self.header(('', 'world')))
        msg.poses = [self.pose() for _ in range(self.pick((0, 1, 3)))]
        return msg


def _barrage(sends: dict[str, tuple[Any, Callable[[], Any]]], count: int) -> None:
    """``count`` rounds of one broken message on every topic of ``sends`` (publisher, maker)."""
    for _ in range(count):
        for publisher, make in sends.values():
            publisher.publish(make())


def _survived(ros: RosHarness, node: Any, what: str) -> dict[str, int]:
    """The node's drops once the barrage has settled; none unexpected, the harness still spins."""
    dropped = ros.wait_until_stable(lambda: dict(node.stats.snapshot().dropped), quiet=1.0, timeout=60.0)
    unexpected = {k: v for k, v in dropped.items() if k.removeprefix('worker_') in UNEXPECTED}
    assert not unexpected, f'{what}: {node.stats.snapshot().summary()}'
    assert ros._thread.is_alive(), f'{what}: the executor stopped'
    return dropped


def _deep() -> Any:
    return qos_profile('reliable', 1000)


def _node(ros: RosHarness, cls: type, **params: Any) -> Any:
    """A node of ``cls`` on the harness with these parameters (dotted names as keywords)."""
    return ros.add(
        cls(context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    )


def _multi_view_node(ros: RosHarness, **params: Any) -> Any:
    """A multi_view_node at 160x120, a keyframe every third frame, deep queues, the filter on
    every frame, no wait for a late camera_info."""
    from depth_fusion_ros.nodes.multi_view_node import MultiViewNode

    filter_params = {'filter.max_lag_frames': 0, 'filter.max_update_rate': 0.0}
    size = {'width': 160, 'height': 120}
    return _node(
        ros, MultiViewNode, keyframe_every=3, queue_size=16, qos_depth=1000, camera_info_wait=0.0,
        **size, **filter_params, **params,
    )  # fmt: skip


def _valid_stream(
    ros: RosHarness, seq: Any, pubs: tuple[Any, Any, Any], image_of: Callable, node: Any
) -> None:
    """The sequence as a camera and a SLAM send it, after the barrage (later stamps); its
    multi-view depth must come out."""
    image, info, pose = pubs
    depth_out = ros.collect(Image, '/depth_fusion/multi_view/depth')
    start = VALID_FROM_S * 10**9
    for i, frame in enumerate(seq.frames):
        stamp = start + round(i * 1e9 / 30)
        header = m.header_msg(stamp, FRAME, kind=K)
        info.publish(m.camera_info_msg(seq.camera, header, kind=K))
        image.publish(image_of(frame.rgb, header))
        pose.publish(m.pose_stamped_msg(seq.poses[i], m.header_msg(stamp, 'world', kind=K), kind=K))
    assert ros.wait_for(lambda: any(m.stamp_to_ns(d.header.stamp) >= start for d in depth_out), 120.0), (
        node.stats.snapshot().summary()
    )
    _survived(ros, node, 'valid stream')


def test_multi_view_node_survives_a_barrage_and_then_maps_a_valid_stream(synthetic_sequence):
    seq = synthetic_sequence
    fuzz = Fuzzer(11)
    with RosHarness() as ros:
        node = _multi_view_node(ros)
        image = ros.publisher(Image, '/camera/rgb/image_color', _deep())
        info = ros.publisher(CameraInfo, '/camera/rgb/camera_info', _deep())
        pose = ros.publisher(PoseStamped, '/camera/pose', _deep())
        assert ros.wait_for_subscribers([image, info, pose])

        def valid_image() -> Any:
            return m.rgb_image_msg(seq.frames[0].rgb, m.header_msg(0, FRAME, kind=K), kind=K)

        def valid_info() -> Any:
            return m.camera_info_msg(seq.camera, m.header_msg(0, FRAME, kind=K), kind=K)

        sends = {
            'image': (image, lambda: fuzz.image(valid_image)),
            'info': (info, lambda: fuzz.camera_info(valid_info)),
            'pose': (pose, lambda: fuzz.pose(seq.poses[0])),
        }
        _barrage(sends, 120)
        dropped = _survived(ros, node, 'barrage')
        assert sum(dropped.values()) >= 120, dropped

        _valid_stream(ros, seq, (image, info, pose), lambda rgb, h: m.rgb_image_msg(rgb, h, kind=K), node)


def _fusion_scene() -> tuple[Any, dict[str, np.ndarray]]:
    from depth_fusion_ros.camera import PinholeCamera

    camera = PinholeCamera(160, 120, 131.25, 131.25, 79.5, 59.5)
    rng = np.random.default_rng(3)
    v, u = np.mgrid[0:120, 0:160].astype(np.float32)
    gt = 2.0 + 0.8 * u / 160 + 0.4 * v / 120
    mv = np.where(rng.random(gt.shape) < 0.05, gt, np.nan).astype(np.float32)
    parts = {
        'single': (1.2 * gt).astype(np.float32),
        'mv': mv,
        'score': np.where(np.isfinite(mv), 0.5, np.nan).astype(np.float32),
        'std': np.where(np.isfinite(mv), 0.05, np.nan).astype(np.float32),
    }
    return camera, {**parts, 'rgb': rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)}


def test_fusion_node_survives_broken_keyframe_parts_and_then_fuses(tmp_path):
    from depth_fusion_ros.nodes.fusion_node import FusionNode

    camera, scene = _fusion_scene()
    fuzz = Fuzzer(12)
    with RosHarness() as ros:
        node = _node(
            ros, FusionNode, queue_size=32, qos_depth=1000, publish_points=False, pair_timeout=0.5,
            **{'fusion.compile_kernel': False},
        )  # fmt: skip
        fused = ros.collect(Image, '/depth_fusion/fused/depth', _deep())
        topics = {
            'info': (CameraInfo, '/depth_fusion/keyframe/camera_info'),
            'image': (Image, '/depth_fusion/keyframe/image'),
            'mv': (Image, '/depth_fusion/multi_view/depth'),
            'score': (Image, '/depth_fusion/multi_view/score'),
            'std': (Image, '/depth_fusion/multi_view/depth_std'),
            'single': (Image, '/depth_fusion/single_view/depth'),
        }
        pubs = {name: ros.publisher(cls, topic, _deep()) for name, (cls, topic) in topics.items()}
        assert ros.wait_for_subscribers(list(pubs.values()))

        def part(name: str, stamp_ns: int) -> Any:
            header = m.header_msg(stamp_ns, FRAME, kind=K)
            if name == 'info':
                return m.camera_info_msg(camera, header, kind=K)
            if name == 'image':
                return m.rgb_image_msg(scene['rgb'], header, kind=K)
            return m.image_msg(scene[name], '32FC1', header, kind=K)

        # Whole keyframes with one part broken: the node pairs them and fuses (or drops) them.
        for _ in range(60):
            stamp = fuzz.stamp_ns()
            broken = fuzz.pick(tuple(topics))
            for name, pub in pubs.items():
                if name != broken:
                    pub.publish(part(name, stamp))
                elif name == 'info':
                    pub.publish(fuzz.camera_info(lambda s=stamp: part('info', s)))
                else:
                    msg = fuzz.image(lambda s=stamp, n=name: part(n, s))
                    msg.header.stamp = (
                        m.time_msg(stamp, kind=K) if fuzz.rng.random() < 0.8 else msg.header.stamp
                    )
                    pub.publish(msg)
        _survived(ros, node, 'barrage')

        stamp = VALID_FROM_S * 10**9
        for name, pub in pubs.items():
            pub.publish(part(name, stamp))
        assert ros.wait_for(lambda: any(m.stamp_to_ns(d.header.stamp) == stamp for d in fused), 60.0), (
            node.stats.snapshot().summary()
        )
        _survived(ros, node, 'valid keyframe')


def test_map_node_survives_broken_keyframes_and_posings_and_then_integrates(tmp_path):
    from map_inputs import MapInputs, make_room, map_node

    _, seq = make_room()
    fuzz = Fuzzer(13)
    with RosHarness() as ros:
        node = map_node(ros, qos_depth=1000, queue_size=32, save_path=str(tmp_path / 'm.ply'))
        inputs = MapInputs(ros)
        posing = {
            'transform': ros.publisher(
                TransformStamped, '/depth_fusion/posing/camera_from_pose_frame', _deep()
            ),
            'time': ros.publisher(TimeReference, '/depth_fusion/posing/pose_time', _deep()),
            'reposed': ros.publisher(PathMsg, '/depth_fusion/posing/reposed_keyframes', _deep()),
            'corrected': ros.publisher(PathMsg, '/camera/corrected_path', _deep()),
        }
        parts = {
            'depth': inputs.depth, 'confidence': inputs.confidence, 'info': inputs.info, 'pose': inputs.pose,
        }  # fmt: skip

        def valid(name: str, i: int, stamp: int) -> Any:
            header = m.header_msg(stamp, FRAME, kind=K)
            if name == 'info':
                return m.camera_info_msg(seq.camera, header, kind=K)
            if name == 'pose':
                return m.pose_stamped_msg(seq.frames[i].pose, m.header_msg(stamp, 'world', kind=K), kind=K)
            array = seq.gt_depth_working(i) if name == 'depth' else np.full((120, 160), 0.8, np.float32)
            return m.image_msg(array, '32FC1', header, kind=K)

        for k in range(60):
            i, stamp = k % len(seq.frames), fuzz.stamp_ns()
            broken = fuzz.pick(tuple(parts))
            for name, pub in parts.items():
                if name != broken:
                    pub.publish(valid(name, i, stamp))
                elif name == 'info':
                    pub.publish(fuzz.camera_info(lambda n=name, j=i, s=stamp: valid(n, j, s)))
                elif name == 'pose':
                    # one world: a map follows another frame on purpose (test_nodes_map.py)
                    msg = fuzz.pose(seq.frames[i].pose, frames=('', 'world'))
                    msg.header.stamp = m.time_msg(stamp, kind=K)
                    pub.publish(msg)
                else:
                    msg = fuzz.image(lambda n=name, j=i, s=stamp: valid(n, j, s))
                    msg.header.stamp = m.time_msg(stamp, kind=K)
                    pub.publish(msg)
            posing['transform'].publish(fuzz.transform())
            posing['time'].publish(fuzz.time_reference())
            posing[fuzz.pick(('reposed', 'corrected'))].publish(fuzz.path())
        _survived(ros, node, 'barrage')

        before = node.stats.snapshot().published.get('integrated', 0)
        start = VALID_FROM_S * 10**9
        for i in range(len(seq.frames)):
            inputs.keyframe(seq, i, start + i * 10**8, skip=('image',))
        assert ros.wait_for(lambda: node.stats.snapshot().published.get('integrated', 0) > before, 60.0), (
            node.stats.snapshot().summary()
        )
        _survived(ros, node, 'valid keyframes')


def test_single_view_node_survives_a_barrage_and_then_predicts(tmp_path):
    import torch
    from conftest import save_torchscript_depth_model

    from depth_fusion_ros.nodes.single_view_node import SingleViewNode

    class _Depth(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return 1.0 + x.mean(dim=1, keepdim=True).abs()

    model = save_torchscript_depth_model(_Depth(), tmp_path, 'fuzz')
    fuzz = Fuzzer(14)
    rgb = fuzz.rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
    with RosHarness() as ros:
        node = _node(ros, SingleViewNode, model=str(model), queue_size=32, qos_depth=1000)
        depth_out = ros.collect(Image, '/depth_fusion/single_view/depth', _deep())
        image = ros.publisher(Image, '/depth_fusion/keyframe/image', _deep())
        info = ros.publisher(CameraInfo, '/depth_fusion/keyframe/camera_info', _deep())
        assert ros.wait_for_subscribers([image, info])

        def valid_image() -> Any:
            return m.rgb_image_msg(rgb, m.header_msg(0, FRAME, kind=K), kind=K)

        _barrage({'image': (image, lambda: fuzz.image(valid_image)), 'info': (info, fuzz.camera_info)}, 80)
        _survived(ros, node, 'barrage')

        stamp = VALID_FROM_S * 10**9
        image.publish(m.rgb_image_msg(rgb, m.header_msg(stamp, FRAME, kind=K), kind=K))
        assert ros.wait_for(lambda: any(m.stamp_to_ns(d.header.stamp) == stamp for d in depth_out), 60.0), (
            node.stats.snapshot().summary()
        )
        _survived(ros, node, 'valid keyframe')


def test_multi_view_node_survives_broken_compressed_images_and_then_maps(synthetic_sequence):
    """image_transport's compressed topic: random bytes, truncated JPEGs, a 16-bit PNG, a
    ``compressedDepth`` format, a camera 2x larger than its camera_info, then a valid stream."""
    import cv2
    from sensor_msgs.msg import CompressedImage

    from depth_fusion_ros.data.compressed import compressed_image_msg, encode_compressed

    seq = synthetic_sequence
    fuzz = Fuzzer(15)
    with RosHarness() as ros:
        node = _multi_view_node(ros, image_transport='compressed')
        image = ros.publisher(CompressedImage, '/camera/rgb/image_color/compressed', _deep())
        info = ros.publisher(CameraInfo, '/camera/rgb/camera_info', _deep())
        pose = ros.publisher(PoseStamped, '/camera/pose', _deep())
        assert ros.wait_for_subscribers([image, info, pose])
        rgb = seq.frames[0].rgb
        jpeg = encode_compressed(rgb, 'jpeg')
        png16 = cv2.imencode('.png', np.full((8, 8), 40000, np.uint16))[1].tobytes()
        big = encode_compressed(np.ascontiguousarray(np.repeat(np.repeat(rgb, 2, 0), 2, 1)), 'jpeg')
        for _ in range(60):
            stamp = fuzz.stamp_ns()
            header = m.header_msg(stamp, FRAME, kind=K)
            info.publish(m.camera_info_msg(seq.camera, header, kind=K))
            pose.publish(m.pose_stamped_msg(seq.poses[0], m.header_msg(stamp, 'world', kind=K), kind=K))
            data, fmt = fuzz.pick(
                (
                    (fuzz.rng.integers(0, 256, 500, dtype=np.uint8).tobytes(), 'rgb8; jpeg compressed bgr8'),
                    (jpeg[: int(fuzz.rng.integers(0, len(jpeg)))], 'rgb8; jpeg compressed bgr8'),
                    (png16, 'mono16; png compressed mono16'),
                    (jpeg, '32FC1; compressedDepth png'),
                    (big, 'rgb8; jpeg compressed bgr8'),
                    (b'', ''),
                )
            )
            image.publish(CompressedImage(header=header, format=fmt, data=data))
        dropped = _survived(ros, node, 'barrage')
        assert sum(dropped.values()) >= 50, dropped

        png = functools.partial(compressed_image_msg, kind=K, fmt='png')
        _valid_stream(ros, seq, (image, info, pose), png, node)
