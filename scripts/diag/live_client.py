"""An independent live client: plays a TUM-layout sequence into the running graph in real time
and scores the fused depth it gets back against the ground truth (diagnostic).

It imports no project code, only rclpy, the standard messages, numpy, OpenCV and PyYAML, the
way a user's (or a reviewer's) own client talks to the graph: colour images, camera_info and
ground-truth poses (PoseStamped, at their own stamps, merged in time order like a SLAM's)
published live at ``--rate`` Hz on the graph's default topics; ``/depth_fusion/fused/depth``,
``/depth_fusion/fused/camera_info`` and ``/depth_fusion/single_view/depth`` received. Each
fused keyframe is scored against the ground-truth depth nearest its stamp, resampled into the
fused depth's camera (the working grid: ``initUndistortRectifyMap`` from the depth camera,
nearest neighbour, where both cameras share the optical centre; each depth point projected from
the colour camera's centre where its YAML gives ``centre_in_depth_camera``, as 7-Scenes' does).
The single-view depth of the same keyframes is the baseline the fusion must beat.

    # the graph, one process per node, on its own ROS domain:
    export ROS_DOMAIN_ID=57
    multi_view_node --ros-args --params-file config/depth_fusion.yaml &
    single_view_node --ros-args --params-file config/depth_fusion.yaml &
    fusion_node --ros-args --params-file config/depth_fusion.yaml &
    python scripts/diag/live_client.py ../shared/data/tum_fr1_xyz_37 --depth-factor 5000
    # 7-Scenes: colour camera from the project's calibration, depth camera from the folder
    python scripts/diag/live_client.py ../shared/data/7scenes_redkitchen_000_499 --frames 150 \
        --camera config/cameras/7scenes_rgb.yaml --depth-factor 5000

Prints one JSON line: frames sent, keyframes fused, fused and single-view MAE over the fused
keyframes, and the latency image sent -> fused received.
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import String


def read_list(path: Path) -> list[tuple[float, list[str]]]:
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith('#'):
            parts = line.split()
            rows.append((float(parts[0]), parts[1:]))
    return rows


def camera(path: Path) -> tuple[int, int, np.ndarray, np.ndarray, str]:
    c = yaml.safe_load(path.read_text())
    k = np.array(c['camera_matrix']['data'], dtype=np.float64).reshape(3, 3)
    d = np.array(c.get('distortion_coefficients', {}).get('data', [0.0] * 5), dtype=np.float64)
    return int(c['image_width']), int(c['image_height']), k, d, c.get('distortion_model', 'plumb_bob')


def colour_centre(path: Path) -> np.ndarray:
    """The colour camera's optical centre in the depth camera's frame (m), where its YAML gives
    one (``centre_in_depth_camera``, 7-Scenes); zero where it does not."""
    given = yaml.safe_load(path.read_text()).get('centre_in_depth_camera', [0.0] * 3)
    return np.array(given, dtype=np.float64)


def projected_depth(
    depth: np.ndarray, dk: np.ndarray, k: np.ndarray, size: tuple[int, int], centre: np.ndarray
) -> np.ndarray:
    """``depth`` (the depth camera's grid, 0 where none) seen from a camera ``k`` at ``centre``
    in the depth camera's frame, on a ``size`` (w, h) grid; the nearest surface where several
    points land on one pixel, 0 where none."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    x = (u - dk[0, 2]) / dk[0, 0] * z - centre[0]
    y = (v - dk[1, 2]) / dk[1, 1] * z - centre[1]
    z = z - centre[2]
    w, h = size
    uc = np.rint(k[0, 0] * x / z + k[0, 2]).astype(np.int64)
    vc = np.rint(k[1, 1] * y / z + k[1, 2]).astype(np.int64)
    inside = (z > 0) & (uc >= 0) & (uc < w) & (vc >= 0) & (vc < h)
    pixel, z = vc[inside] * w + uc[inside], z[inside]
    order = np.lexsort((z, pixel))
    pixel, z = pixel[order], z[order]
    first = np.r_[True, pixel[1:] != pixel[:-1]]
    out = np.zeros(h * w, dtype=np.float32)
    out[pixel[first]] = z[first]
    return out.reshape(h, w)


def stamp_of(t: float):
    from builtin_interfaces.msg import Time

    sec = int(t)
    return Time(sec=sec, nanosec=round((t - sec) * 1e9))


class Client:
    def __init__(self, node, args) -> None:
        self.node = node
        reliable = QoSProfile(
            depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST
        )
        if args.compressed:  # image_transport's convention: <image>/compressed, format 'jpeg'
            self.image_pub = node.create_publisher(
                CompressedImage, '/camera/rgb/image_color/compressed', reliable
            )
        else:
            self.image_pub = node.create_publisher(Image, '/camera/rgb/image_color', reliable)
        self.info_pub = node.create_publisher(CameraInfo, '/camera/rgb/camera_info', reliable)
        self.pose_pub = node.create_publisher(PoseStamped, '/camera/pose', reliable)
        self.fused: dict[int, tuple[np.ndarray, float]] = {}
        self.single: dict[int, np.ndarray] = {}
        #: arrival time of each stage's output per keyframe stamp: where the latency is spent
        self.arrivals: dict[str, dict[int, float]] = {'multi_view': {}, 'single_view': {}}
        self.fused_k: np.ndarray | None = None
        self.sent_at: dict[int, float] = {}
        node.create_subscription(Image, '/depth_fusion/fused/depth', self._on_fused, reliable)
        node.create_subscription(Image, '/depth_fusion/single_view/depth', self._on_single, reliable)
        node.create_subscription(CameraInfo, '/depth_fusion/fused/camera_info', self._on_info, reliable)
        node.create_subscription(
            Image, '/depth_fusion/multi_view/depth', lambda m: self._arrived('multi_view', m), reliable
        )
        self.decisions: dict[int, dict] = {}
        node.create_subscription(String, '/depth_fusion/fused/decision', self._on_decision, reliable)

    @staticmethod
    def _key(msg) -> int:
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec

    @staticmethod
    def _depth(msg: Image) -> np.ndarray:
        assert msg.encoding == '32FC1', msg.encoding
        return np.frombuffer(bytes(msg.data), dtype=np.float32).reshape(msg.height, msg.width).copy()

    def _on_fused(self, msg: Image) -> None:
        self.fused[self._key(msg)] = (self._depth(msg), time.monotonic())

    def _on_single(self, msg: Image) -> None:
        self.single[self._key(msg)] = self._depth(msg)
        self._arrived('single_view', msg)

    def _arrived(self, stage: str, msg) -> None:
        self.arrivals[stage].setdefault(self._key(msg), time.monotonic())

    def _on_decision(self, msg: String) -> None:
        try:
            verdict = json.loads(msg.data)
            stamp_ns = verdict.get('stamp_ns')  # exact (decision_json); 'stamp' is seconds
            if stamp_ns is None:
                stamp_ns = round(float(verdict['stamp']) * 1e9)
            self.decisions[int(stamp_ns)] = verdict
        except (ValueError, KeyError, TypeError) as exc:
            print(f'unreadable decision: {exc}', file=sys.stderr)

    def _on_info(self, msg: CameraInfo) -> None:
        self.fused_k = np.array(msg.k, dtype=np.float64).reshape(3, 3)


def stage_latencies(client: Client) -> dict[str, float]:
    """Median seconds from an image sent to each stage's output seen here (keyframes that got one)."""
    out = {}
    for stage, at in client.arrivals.items():
        delays = [t - client.sent_at[k] for k, t in at.items() if k in client.sent_at]
        if delays:
            out[stage] = round(float(np.median(delays)), 3)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('sequence', type=Path)
    p.add_argument('--camera', type=Path, help='colour camera YAML (default: the folder camera.yaml)')
    p.add_argument('--depth-camera', type=Path, help='ground-truth depth camera YAML (default: camera.yaml)')
    p.add_argument('--depth-factor', type=float, default=5000.0, help='depth PNG units per metre')
    p.add_argument('--frames', type=int, default=0, help='first N frames (0: all)')
    p.add_argument(
        '--rate',
        type=float,
        default=30.0,
        help='play the stamps at rate / 30 of real time (30: as recorded, whatever the camera rate; '
        '60: twice as fast)',
    )
    p.add_argument('--start-delay', type=float, default=3.0, help='s after discovery, then play')
    p.add_argument('--compressed', action='store_true', help='publish JPEG CompressedImage (image_transport)')
    p.add_argument(
        '--upscale',
        type=float,
        default=1.0,
        help='resize the colour images by this factor (and the camera with them) before streaming: '
        'a larger camera than the sequence was recorded with (e.g. 2.025: 1296x972)',
    )
    p.add_argument(
        '--decisions', action='store_true', help='print each scored keyframe with its fusion decision'
    )
    p.add_argument('--drain', type=float, default=8.0, help='seconds without a fused depth that end the wait')
    p.add_argument(
        '--no-wait-output',
        dest='wait_output',
        action='store_false',
        help='start as soon as the graph subscribes to the images, before this client sees the fused output',
    )
    args = p.parse_args(argv)
    seq = args.sequence
    width, height, k, d, model = camera(args.camera or seq / 'camera.yaml')
    if args.upscale != 1.0:  # pixel centres at integers: x' = (x + 0.5) f - 0.5
        width, height = round(width * args.upscale), round(height * args.upscale)
        k = k.copy()
        k[0, 0] *= args.upscale
        k[1, 1] *= args.upscale
        k[0, 2] = (k[0, 2] + 0.5) * args.upscale - 0.5
        k[1, 2] = (k[1, 2] + 0.5) * args.upscale - 0.5
    _, _, dk, dd, _ = camera(args.depth_camera or seq / 'camera.yaml')
    centre = colour_centre(args.camera) if args.camera else np.zeros(3)
    images = read_list(seq / 'rgb.txt')
    if args.frames:
        images = images[: args.frames]
    depths = read_list(seq / 'depth.txt')
    depth_times = [t for t, _ in depths]
    poses = [(t, [float(v) for v in rest]) for t, rest in read_list(seq / 'groundtruth.txt')]
    t0, t1 = images[0][0] - 0.1, images[-1][0] + 0.1
    poses = [(t, v) for t, v in poses if t0 <= t <= t1]

    rclpy.init()
    node = rclpy.create_node('independent_live_client')
    client = Client(node, args)
    deadline = time.monotonic() + 30.0

    def matched() -> bool:
        # the graph subscribed to the images, and this client knows the fusion node's writer
        # (without the second, its first fused depths can be published before it listens)
        return client.image_pub.get_subscription_count() > 0 and (
            not args.wait_output or node.count_publishers('/depth_fusion/fused/depth') > 0
        )

    while not matched() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    end_delay = time.monotonic() + args.start_delay
    while time.monotonic() < end_delay:
        rclpy.spin_once(node, timeout_sec=0.05)

    info = CameraInfo(width=width, height=height, distortion_model=model)
    info.k = k.ravel().tolist()
    info.d = d.tolist()
    info.r = np.eye(3).ravel().tolist()
    proj = np.zeros((3, 4))
    proj[:, :3] = k
    info.p = proj.ravel().tolist()
    events = [(t, 'pose', v) for t, v in poses] + [(t, 'image', rest[0]) for t, rest in images]
    loaded = {}  # read, resized and encoded before the stream: the client's own cost stays out of it
    for _, rest in images:
        bgr = cv2.imread(str(seq / rest[0]), cv2.IMREAD_COLOR)
        if args.upscale != 1.0:
            bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_LINEAR)
        if args.compressed:
            loaded[rest[0]] = cv2.imencode('.jpg', bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
        else:
            loaded[rest[0]] = bgr
    events.sort(key=lambda e: (e[0], e[1] == 'image'))
    start_wall, start_stamp = time.monotonic(), images[0][0]
    for t, kind, payload in events:
        due = start_wall + max(0.0, t - start_stamp) / (args.rate / 30.0)
        while time.monotonic() < due:
            rclpy.spin_once(node, timeout_sec=max(0.0, min(0.005, due - time.monotonic())))
        if kind == 'pose':
            msg = PoseStamped()
            msg.header.stamp, msg.header.frame_id = stamp_of(t), 'world'
            tx, ty, tz, qx, qy, qz, qw = payload
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = tx, ty, tz
            msg.pose.orientation.x, msg.pose.orientation.y = qx, qy
            msg.pose.orientation.z, msg.pose.orientation.w = qz, qw
            client.pose_pub.publish(msg)
            continue
        if args.compressed:
            img = CompressedImage(format='bgr8; jpeg compressed bgr8')
            img.data = loaded[payload]
        else:
            bgr = loaded[payload]
            img = Image(height=bgr.shape[0], width=bgr.shape[1], encoding='bgr8', step=bgr.shape[1] * 3)
            img.data = bgr.tobytes()
        img.header.stamp, img.header.frame_id = stamp_of(t), 'camera_rgb_optical_frame'
        info.header = img.header
        client.info_pub.publish(info)
        client.image_pub.publish(img)
        client.sent_at[Client._key(img)] = time.monotonic()
    stream_s = time.monotonic() - start_wall
    last = time.monotonic()
    seen = len(client.fused)
    while time.monotonic() - last < args.drain:
        rclpy.spin_once(node, timeout_sec=0.1)
        if len(client.fused) != seen:
            seen, last = len(client.fused), time.monotonic()

    fused_err, single_err, worse, latencies, ratios = [], [], 0, [], []
    maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}  # the depth camera -> fused grid
    for key, (fused, received) in sorted(client.fused.items()):
        latencies.append(received - client.sent_at.get(key, received))
        t = key / 1e9
        i = bisect.bisect_left(depth_times, t)
        near = min((j for j in (i - 1, i) if 0 <= j < len(depths)), key=lambda j: abs(depth_times[j] - t))
        if abs(depth_times[near] - t) > 0.03 or client.fused_k is None:
            continue
        gt_png = cv2.imread(str(seq / depths[near][1][0]), cv2.IMREAD_UNCHANGED)
        gt_raw = np.where(gt_png == 65535, 0, gt_png).astype(np.float32) / args.depth_factor  # 65535: none
        gh, gw = fused.shape
        if centre.any():  # the colour camera beside the depth camera: each point from its centre
            undistorted = gt_raw
            if dd.any():  # nearest neighbour: a blend across an edge is a depth nothing has
                size = gt_raw.shape[::-1]
                plain = cv2.initUndistortRectifyMap(dk, dd, np.eye(3), dk, size, cv2.CV_32FC1)
                undistorted = cv2.remap(gt_raw, *plain, cv2.INTER_NEAREST, borderValue=0.0)
            gt = projected_depth(undistorted, dk, client.fused_k, (gw, gh), centre)
        else:
            if (gh, gw) not in maps:  # the fused camera is the same for every keyframe of a stream
                maps[gh, gw] = cv2.initUndistortRectifyMap(
                    dk, dd, np.eye(3), client.fused_k, (gw, gh), cv2.CV_32FC1
                )
            gt = cv2.remap(gt_raw, *maps[gh, gw], cv2.INTER_NEAREST, borderValue=0.0)
        valid = (gt > 0) & np.isfinite(fused)
        single = client.single.get(key)
        paired = single is not None and single.shape == fused.shape
        if paired:
            valid &= np.isfinite(single)
            single_err.append(float(np.abs(single - gt)[valid].mean()))
        fused_err.append(float(np.abs(fused - gt)[valid].mean()))
        worse += paired and fused_err[-1] > single_err[-1]
        if args.decisions and paired:
            near = min(client.decisions, key=lambda k: abs(k - key), default=None)
            verdict = client.decisions.get(near) if near is not None and abs(near - key) < 1_000_000 else None
            ratio = fused_err[-1] / single_err[-1]
            print(
                json.dumps(
                    {
                        'keyframe': t,
                        'fused_mae_m': round(fused_err[-1], 4),
                        'single_view_mae_m': round(single_err[-1], 4),
                        'ratio': ratio,
                        'decision': verdict,
                    }
                )
            )
        if paired and single_err[-1] > 0:
            ratios.append(round(fused_err[-1] / single_err[-1], 3))
    summary = {
        'sequence': seq.name,
        'frames_sent': len(images),
        'stream_seconds': round(stream_s, 2),
        'fused_received': len(client.fused),
        'scored': len(fused_err),
        'fused_mae_m': round(float(np.mean(fused_err)), 4) if fused_err else None,
        'single_view_mae_m': round(float(np.mean(single_err)), 4) if single_err else None,
        'fused_worse_keyframes': int(worse),
        # fused / single-view MAE per paired keyframe, in stream order (1.0: the single view as it is)
        'fused_over_single': ratios,
        'latency_median_s': round(float(np.median(latencies)), 3) if latencies else None,
        # image sent -> each stage's output seen here, median over the keyframes that reached it
        'stage_latency_median_s': stage_latencies(client),
    }
    print(json.dumps(summary))
    node.destroy_node()
    rclpy.shutdown()
    return 0 if client.fused else 1


if __name__ == '__main__':
    sys.exit(main())
