"""Raw 640x480 images and poses from one process: how many arrive, and how far the poses lag.

    python scripts/diag/image_pose_lag.py sub [--seconds 20] &        # the graph's side
    python scripts/diag/image_pose_lag.py pub [--frames 150] [--best-effort]

Run the subscriber with or without ``FASTRTPS_DEFAULT_PROFILES_FILE`` pointing at the
package's profile (``depth_fusion_ros/config/fastdds_shm.xml``, whose reader profile puts
``/camera/rgb/image_color`` on UDP) and the publisher with Fast DDS's defaults, as a camera
driver or a user's client runs; the same ``ROS_DOMAIN_ID`` on both. The subscriber prints the
images and poses received and, at each image, the newest image stamp minus the newest pose
stamp (docs/nodes.md, "Large raw images").
"""

import argparse
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

TOPIC_IMAGE, TOPIC_POSE = '/camera/rgb/image_color', '/camera/pose'


def qos(best_effort: bool) -> QoSProfile:
    reliability = ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE
    return QoSProfile(depth=100, reliability=reliability, history=HistoryPolicy.KEEP_LAST)


def publish(node, frames: int, best_effort: bool) -> None:
    images = node.create_publisher(Image, TOPIC_IMAGE, qos(best_effort))
    poses = node.create_publisher(PoseStamped, TOPIC_POSE, qos(best_effort))
    deadline = time.monotonic() + 20
    while images.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    data = np.random.default_rng(0).integers(0, 255, 480 * 640 * 3, dtype=np.uint8).tobytes()
    image = Image(height=480, width=640, encoding='rgb8', step=640 * 3, data=data)
    for i in range(frames):
        image.header.stamp.sec, image.header.stamp.nanosec = 100 + i // 30, (i % 30) * 33_333_333
        poses.publish(PoseStamped(header=image.header))
        images.publish(image)
        time.sleep(1 / 30)
    time.sleep(2.0)


def subscribe(node, seconds: float, best_effort: bool) -> None:
    seen: dict[str, list[float]] = {'image': [], 'pose': []}
    lags: list[float] = []

    def stamp(msg) -> float:
        return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    def on_image(msg) -> None:
        seen['image'].append(stamp(msg))
        if seen['pose']:
            lags.append(seen['image'][-1] - max(seen['pose']))

    node.create_subscription(Image, TOPIC_IMAGE, on_image, qos(best_effort))
    node.create_subscription(
        PoseStamped, TOPIC_POSE, lambda m: seen['pose'].append(stamp(m)), qos(best_effort)
    )
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    worst = max(lags) if lags else float('nan')
    late = sum(lag > 0.5 for lag in lags)
    print(
        f'images {len(seen["image"])} poses {len(seen["pose"])} '
        f'pose lag max {worst:.3f} s, over 0.5 s at {late}'
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('side', choices=('pub', 'sub'))
    p.add_argument('--frames', type=int, default=150)
    p.add_argument('--seconds', type=float, default=20.0)
    p.add_argument(
        '--best-effort', action='store_true', help="best-effort QoS (a camera driver's sensor_data)"
    )
    args = p.parse_args()
    rclpy.init()
    node = rclpy.create_node(f'image_pose_lag_{args.side}')
    if args.side == 'pub':
        publish(node, args.frames, args.best_effort)
    else:
        subscribe(node, args.seconds, args.best_effort)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == '__main__':
    main()
