"""map_node's memory, fed over DDS alone: how the heap and the process grow (diagnostic).

    python scripts/diag/map_memory.py --rate 8 --seconds 180 [-- -p reintegration_max_mb:=16.0]

Starts ``map_node`` (default parameters, ``map.max_blocks`` 300, its own ROS domain) in a
process that also prints glibc's ``mallinfo2`` every 20 s (heap size, in use, free, free
chunks, mmapped), and publishes fused keyframes (depth, confidence, camera_info, pose, colour)
of a synthetic room (320x240, 100 frames), looped, at ``--rate`` keyframes a second. Then prints the
node's lines and final counters. What docs/mapping.md "Looped replays" measured with it:
free heap memory and free chunks growing while what is in use stays flat is fragmentation.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

#: Runs map_node's main with a thread that prints mallinfo2 (glibc >= 2.33).
_NODE = r"""
import ctypes, sys, threading, time
from depth_fusion_ros.nodes.map_node import main
class MI2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ('arena', 'ordblks', 'smblks', 'hblks', 'hblkhd',
                                               'usmblks', 'fsmblks', 'uordblks', 'fordblks', 'keepcost')]
libc = ctypes.CDLL('libc.so.6')
libc.mallinfo2.restype = MI2
def watch():
    t0 = time.monotonic()
    while True:
        time.sleep(20)
        mi, M = libc.mallinfo2(), 2**20
        anon = [l for l in open('/proc/self/status') if l.startswith('RssAnon')][0].split()[1]
        print(f'MEMORY t {time.monotonic() - t0:4.0f} s  anonymous {int(anon) / 1024:5.0f} MB  heap '
              f'{mi.arena / M:4.0f} (in use {mi.uordblks / M:4.0f}, free {mi.fordblks / M:4.0f} in '
              f'{mi.ordblks} chunks)  mmapped {mi.hblkhd / M:3.0f} MB', flush=True)
threading.Thread(target=watch, daemon=True).start()
sys.exit(main(sys.argv[1:]))
"""


def feed(rate: float, seconds: float) -> int:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image

    from depth_fusion_ros.data import messages as m
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
    from depth_fusion_ros.nodes.qos import qos_profile

    seq = render_sequence(SynthConfig(width=320, height=240, frames=100, seed=0))
    frames = [(f.rgb, seq.gt_depth_working(i), f.pose) for i, f in enumerate(seq.frames)]
    rclpy.init()
    node = Node('map_memory_feeder')
    q = qos_profile('reliable', 10)
    pub = {
        'depth': node.create_publisher(Image, '/depth_fusion/fused/depth', q),
        'confidence': node.create_publisher(Image, '/depth_fusion/fused/confidence', q),
        'info': node.create_publisher(CameraInfo, '/depth_fusion/fused/camera_info', q),
        'pose': node.create_publisher(PoseStamped, '/depth_fusion/keyframe/pose', q),
        'rgb': node.create_publisher(Image, '/depth_fusion/keyframe/image', q),
    }
    time.sleep(3.0)  # discovery
    rng = np.random.default_rng(0)
    confidence = np.full((seq.camera.height, seq.camera.width), 0.8, np.float32)
    t0, k = time.monotonic(), 0
    while time.monotonic() - t0 < seconds:
        rgb, depth, pose = frames[(k * 5) % len(frames)]  # every 5th frame a keyframe, looped
        noisy = (depth * (1 + 0.01 * rng.standard_normal(depth.shape))).astype(np.float32)
        ns = int((1000 + k / rate) * 1e9)
        header = m.header_msg(ns, 'camera', kind=m.RCLPY)
        pub['info'].publish(m.camera_info_msg(seq.camera, header, kind=m.RCLPY))
        pub['rgb'].publish(m.image_msg(rgb, 'rgb8', header, kind=m.RCLPY))
        pub['pose'].publish(m.pose_stamped_msg(pose, m.header_msg(ns, 'world', kind=m.RCLPY), kind=m.RCLPY))
        pub['confidence'].publish(m.image_msg(confidence, '32FC1', header, kind=m.RCLPY))
        pub['depth'].publish(m.image_msg(noisy, '32FC1', header, kind=m.RCLPY))
        k += 1
        time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
    node.destroy_node()
    rclpy.shutdown()
    return k


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rate', type=float, default=6.0, help='keyframes per second')
    p.add_argument('--seconds', type=float, default=180.0)
    p.add_argument('node_args', nargs='*', help='more map_node arguments (after --)')
    args = p.parse_args()
    from depth_fusion_ros.nodes.graph.isolation import pick_free_domain
    from depth_fusion_ros.nodes.testing import TEST_DOMAINS

    domain, lock = pick_free_domain(TEST_DOMAINS)
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    config = str(ROOT / 'config/depth_fusion.yaml')
    command = [sys.executable, '-c', _NODE, '--ros-args', '--params-file', config]
    command += ['-p', 'map.max_blocks:=300', *args.node_args]
    node = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        time.sleep(6.0)  # the node's start
        sent = feed(args.rate, args.seconds)
    finally:
        node.send_signal(2)
        out, _ = node.communicate(timeout=60)
        lock.close()
    for line in out.splitlines():
        if line.startswith('MEMORY') or 'final counters' in line:
            print(line)
    print(f'{sent} keyframes sent at {args.rate:g} a second')
    return 0


if __name__ == '__main__':
    sys.exit(main())
