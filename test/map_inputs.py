"""map_node test inputs over DDS: fused keyframes of a synthetic room, and service calls."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from std_srvs.srv import Trigger

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.data.synthetic import SynthConfig, build_world, render_sequence
from depth_fusion_ros.nodes.map_node import MapNode
from depth_fusion_ros.nodes.testing import RosHarness

K = m.RCLPY
FRAME = 'camera_rgb_optical_frame'
T0 = 1_000_000_000


def make_room():
    """A 16-frame synthetic room at 160x120 (its scene, for the geometry checks, and the sequence)."""
    cfg = SynthConfig(width=160, height=120, frames=16, seed=7)
    return build_world(cfg)[0], render_sequence(cfg)


class MapInputs:
    """Publishers of what map_node takes: a keyframe's fused depth, confidence, camera_info, pose, image."""

    def __init__(self, ros: RosHarness) -> None:
        self.depth = ros.publisher(Image, '/depth_fusion/fused/depth')
        self.confidence = ros.publisher(Image, '/depth_fusion/fused/confidence')
        self.info = ros.publisher(CameraInfo, '/depth_fusion/fused/camera_info')
        self.pose = ros.publisher(PoseStamped, '/depth_fusion/keyframe/pose')
        self.image = ros.publisher(Image, '/depth_fusion/keyframe/image')
        assert ros.wait_for_subscribers([self.depth, self.confidence, self.info, self.pose, self.image])

    def keyframe(self, seq, i: int, stamp_ns: int, skip: tuple[str, ...] = (), pose=None) -> None:
        header = m.header_msg(stamp_ns, FRAME, kind=K)
        world = m.header_msg(stamp_ns, 'world', kind=K)
        depth = seq.gt_depth_working(i)
        confidence = np.full(depth.shape, 0.8, np.float32)
        parts = {
            'image': lambda: self.image.publish(m.rgb_image_msg(seq.frames[i].rgb, header, kind=K)),
            'info': lambda: self.info.publish(m.camera_info_msg(seq.camera, header, kind=K)),
            'depth': lambda: self.depth.publish(m.depth_image_msg(depth, header, kind=K)),
            'confidence': lambda: self.confidence.publish(m.image_msg(confidence, '32FC1', header, kind=K)),
            'pose': lambda: self.pose.publish(pose or m.pose_stamped_msg(seq.frames[i].pose, world, kind=K)),
        }
        for name, send in parts.items():
            if name not in skip:
                send()


def map_node(ros: RosHarness, **params) -> MapNode:
    overrides = [Parameter('queue_size', value=16), *(Parameter(k, value=v) for k, v in params.items())]
    return ros.add(MapNode(context=ros.context, parameter_overrides=overrides))


def call(ros: RosHarness, service: str) -> Trigger.Response:
    client = ros.probe.create_client(Trigger, service)
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    assert ros.wait_for(future.done, 30.0)
    return future.result()


def call_save(ros: RosHarness) -> Trigger.Response:
    return call(ros, '/map_node/save_map')
