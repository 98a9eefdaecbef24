"""Best-effort 640x480 images between two processes: how many arrive (Fast DDS shared memory).

    python scripts/diag/shm_images.py be|rel sub   # in one shell (or backgrounded) first
    python scripts/diag/shm_images.py be|rel pub   # then: 60 images at 30 Hz

Run each side with or without ``FASTRTPS_DEFAULT_PROFILES_FILE`` pointing at the package's
profile (``depth_fusion_ros/config/fastdds_shm.xml``); the subscriber prints ``received N``
after 12 s. Use the same ``ROS_DOMAIN_ID`` on both sides.
"""

import sys
import time

import numpy as np
import rclpy
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

reliability, side = sys.argv[1], sys.argv[2]
rclpy.init()
node = rclpy.create_node(f'shm_images_{side}')
qos = QoSProfile(
    depth=10,
    reliability=ReliabilityPolicy.BEST_EFFORT if reliability == 'be' else ReliabilityPolicy.RELIABLE,
    history=HistoryPolicy.KEEP_LAST,
)
if side == 'pub':
    pub = node.create_publisher(Image, '/shm_images', qos)
    start = time.time()
    while pub.get_subscription_count() == 0 and time.time() - start < 10:
        time.sleep(0.05)
    time.sleep(0.5)
    data = np.random.default_rng(0).integers(0, 255, 480 * 1920, dtype=np.uint8).tobytes()
    msg = Image(height=480, width=640, encoding='rgb8', step=1920, data=data)
    for i in range(60):
        msg.header.frame_id = str(i)
        pub.publish(msg)
        time.sleep(1 / 30)
    time.sleep(1.0)
else:
    got = []
    node.create_subscription(Image, '/shm_images', lambda m: got.append(m.header.frame_id), qos)
    start = time.time()
    while time.time() - start < 12:
        rclpy.spin_once(node, timeout_sec=0.1)
    print('received', len(got))
