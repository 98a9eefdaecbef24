"""Camera images over UDP: the reader profiles, their topic resolution, and a publisher with
Fast DDS's defaults whose poses no longer stall behind its raw images (two real processes)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from depth_fusion_ros.nodes.graph.dds import PROFILE_ENV, fastdds_profile_path, profile_for_console_node
from depth_fusion_ros.nodes.graph.dds_readers import profile_with_udp_readers, reader_topics, resolved_topic

IMAGE = 'camera/rgb/image_color'
NODE = 'multi_view_node'


def test_image_topic_is_resolved_with_the_command_line_remaps_and_namespace():
    assert resolved_topic(IMAGE, NODE, []) == '/camera/rgb/image_color'
    assert resolved_topic(IMAGE, NODE, ['prog', '--ros-args', '-r', f'{IMAGE}:=/cam/image']) == '/cam/image'
    assert resolved_topic(IMAGE, NODE, ['--ros-args', '--remap', f'/{IMAGE}:=img']) == '/img'
    assert (
        resolved_topic(IMAGE, NODE, ['--ros-args', '-r', '__ns:=/robot1']) == '/robot1/camera/rgb/image_color'
    )
    # a rule for another node, or outside --ros-args, does not apply; one for this node does
    assert resolved_topic(IMAGE, NODE, ['--ros-args', '-r', f'other:{IMAGE}:=/no']) == f'/{IMAGE}'
    argv = ['--ros-args', '-r', f'{NODE}:{IMAGE}:=/yes', '--', '-r', f'{IMAGE}:=/ignored']
    assert resolved_topic(IMAGE, NODE, argv) == '/yes'
    # the node renamed: its rules follow the new name
    argv = ['--ros-args', '-r', '__node:=mv2', '-r', f'mv2:{IMAGE}:=/renamed']
    assert resolved_topic(IMAGE, NODE, argv) == '/renamed'


def test_the_package_profile_names_the_default_image_topics_and_a_copy_names_others(tmp_path):
    package = fastdds_profile_path()
    named = reader_topics(package.read_text())
    assert {'/camera/rgb/image_color', '/camera/rgb/image_color/compressed'} <= named
    assert profile_with_udp_readers(package, ['/camera/rgb/image_color'], tmp_path) == package
    copy = profile_with_udp_readers(package, ['/cam/image', '/cam/image/compressed'], tmp_path)
    assert copy.parent == tmp_path and copy != package
    root = ET.parse(copy).getroot()  # well formed, and Fast DDS's own elements kept
    readers = [e.get('profile_name') for e in root.iter() if e.tag.endswith('data_reader')]
    assert {'/cam/image', '/cam/image/compressed'} <= set(readers) and len(readers) == len(set(readers))
    assert any(e.tag.endswith('participant') for e in root.iter())
    # the same topics again: the same file, written once
    assert profile_with_udp_readers(package, ['/cam/image', '/cam/image/compressed'], tmp_path) == copy


def test_a_console_node_gets_the_copy_only_when_no_profile_is_set(tmp_path, monkeypatch):
    monkeypatch.setenv('XDG_CACHE_HOME', str(tmp_path))
    env: dict[str, str] = {}
    line = profile_for_console_node(env, ['/cam/image'])
    path = Path(env[PROFILE_ENV[0]])
    assert path.parent == tmp_path / 'depth_fusion_ros' / 'fastdds' and '/cam/image read over UDP' in line
    env = {}
    profile_for_console_node(env, ['/camera/rgb/image_color'])
    assert env[PROFILE_ENV[0]] == str(fastdds_profile_path())
    mine = {'FASTDDS_DEFAULT_PROFILES_FILE': '/etc/my_profile.xml'}
    assert 'yours' in profile_for_console_node(mine, ['/cam/image'])
    assert mine == {'FASTDDS_DEFAULT_PROFILES_FILE': '/etc/my_profile.xml'}


FRAMES = 150
PUBLISHER = """
import time, numpy as np, rclpy
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image
rclpy.init()
node = rclpy.create_node('default_camera_client')
images = node.create_publisher(Image, '/camera/rgb/image_color', 100)
infos = node.create_publisher(CameraInfo, '/camera/rgb/camera_info', 100)
poses = node.create_publisher(PoseStamped, '/camera/pose', 100)
deadline = time.monotonic() + 20
matched = lambda: images.get_subscription_count() and poses.get_subscription_count()
while not matched() and time.monotonic() < deadline:
    time.sleep(0.05)
time.sleep(0.5)
data = np.random.default_rng(0).integers(0, 255, 480 * 640 * 3, dtype=np.uint8).tobytes()
image = Image(height=480, width=640, encoding='rgb8', step=640 * 3, data=data)
for i in range(FRAMES):
    image.header.stamp.sec, image.header.stamp.nanosec = 100 + i // 30, (i % 30) * 33_000_000
    poses.publish(PoseStamped(header=image.header))
    infos.publish(CameraInfo(header=image.header, width=640, height=480))
    images.publish(image)
    time.sleep(1 / 30)
time.sleep(2.0)
"""

SUBSCRIBER = """
import json, sys, time, rclpy
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image
rclpy.init()
node = rclpy.create_node('graph_side')
seen = {'image': [], 'pose': []}
stamp = lambda m: m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
node.create_subscription(Image, '/camera/rgb/image_color', lambda m: seen['image'].append(stamp(m)), 100)
node.create_subscription(PoseStamped, '/camera/pose', lambda m: seen['pose'].append(stamp(m)), 100)
deadline = time.monotonic() + float(sys.argv[1])
lag = 0.0
while time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.02)
    if seen['image'] and seen['pose']:
        lag = max(lag, seen['image'][-1] - max(seen['pose']))
    if len(seen['image']) >= FRAMES and len(seen['pose']) >= FRAMES:
        break
print(json.dumps({'images': len(seen['image']), 'poses': len(seen['pose']), 'max_pose_lag_s': lag}))
"""


def test_poses_from_a_default_publisher_of_raw_images_do_not_stall(tmp_path):
    """One process with Fast DDS's defaults publishes raw 640x480 images and poses (reliable,
    30 Hz), as a user's client or a camera driver would; the receiving process has the
    package profile. Through shared memory the poses stalled 1.5-3 s at a time behind the
    images; over UDP (the image topic's reader profile) they keep pace."""
    (tmp_path / 'pub.py').write_text(f'FRAMES = {FRAMES}\n' + PUBLISHER)
    (tmp_path / 'sub.py').write_text(f'FRAMES = {FRAMES}\n' + SUBSCRIBER)
    base = {k: v for k, v in os.environ.items() if k not in PROFILE_ENV and k != 'FASTDDS_BUILTIN_TRANSPORTS'}
    graph_env = {**base, PROFILE_ENV[0]: str(fastdds_profile_path())}
    sub = subprocess.Popen(
        [sys.executable, str(tmp_path / 'sub.py'), '40'], env=graph_env, stdout=subprocess.PIPE, text=True
    )
    try:
        subprocess.run([sys.executable, str(tmp_path / 'pub.py')], env=base, check=True, timeout=60)
        out, _ = sub.communicate(timeout=60)
    finally:
        sub.kill()
    result = json.loads(out.strip().splitlines()[-1])
    assert result['images'] == FRAMES and result['poses'] == FRAMES, result
    assert result['max_pose_lag_s'] < 0.5, result
