"""Small bags and a params file for the ``depth-fusion run`` fault and isolation tests.

Kept cheap for a loaded 2-core CI machine: 9 synthetic frames (320x240), a keyframe every 3rd
(2 keyframes), a TorchScript stand-in network, lossless queues.
"""

from __future__ import annotations

from pathlib import Path

KEYFRAME_EVERY = 3
FRAMES = 9
TOPIC_IMAGE = '/camera/rgb/image_color'


def small_bag(tum_dir: Path, out: Path, frames: int = FRAMES, storage: str = 'mcap') -> Path:
    from depth_fusion_ros.data.rosbag_convert import tum_to_rosbag

    return tum_to_rosbag(tum_dir, out, max_frames=frames, storage=storage, show_progress=False).path


def shifted_copy(bag: Path, out: Path, shift_ns: int, drop: tuple[str, ...] = ()) -> Path:
    """``bag`` with every header stamp and log time moved by ``shift_ns`` (a different stream
    with the same content), without the topics in ``drop``."""
    from rosbags.rosbag2 import Reader

    from depth_fusion_ros.data.rosbag_convert import AtomicBagWriter
    from depth_fusion_ros.nodes.bag_replayer import has_leading_header, shift_header_stamp

    with Reader(bag) as reader, AtomicBagWriter(out) as writer:
        for conn, t_ns, raw in reader.messages():
            if conn.topic in drop:
                continue
            data = shift_header_stamp(bytes(raw), shift_ns) if has_leading_header(conn.msgtype) else raw
            writer.write_raw(conn.topic, conn.msgtype, t_ns + shift_ns, data)
    return out


def header_stamps(bag: Path, topic: str) -> set[int]:
    from depth_fusion_ros.data.rosbag_read import iter_messages

    return {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, _, m in iter_messages(bag, [topic])}


def write_params(path: Path, model: Path, extra_replayer: str = '') -> Path:
    """The graph's parameters: lossless queues, a keyframe every 3rd frame, the toy network."""
    path.write_text(
        f"""\
/**:
  ros__parameters:
    queue_size: 16
    queue_policy: block
    qos_depth: 100
    stats_period: 0.0
multi_view_node:
  ros__parameters:
    keyframe_every: {KEYFRAME_EVERY}
single_view_node:
  ros__parameters:
    model: '{model}'
fusion_node:
  ros__parameters:
    publish_points: false
    pair_timeout: 300.0
    fusion.compile_kernel: false
bag_replayer:
  ros__parameters:
    rate: 1.0
{extra_replayer}"""
    )
    return path
