"""Write rosbag2 recordings (mcap or sqlite3) from TUM folders and recorded bags (ROS 1 ``.bag``
files, a robot's own rosbag2): ``convert()``.

The output is raw sensor data in the layout every node and ``load_bag_sequence`` expect
(docs/data.md). The camera topics are written per colour frame, stamped with the colour
image's stamp; the pose topic carries the pose source's own samples at their own stamps
(header stamp = bag time throughout):

==========================  ==============================  =====================================
topic (default)             type                            content
==========================  ==============================  =====================================
/camera/rgb/image_color     sensor_msgs/Image rgb8          original colour, NOT undistorted
/camera/rgb/camera_info     sensor_msgs/CameraInfo          K and D, one per colour frame
/camera/depth/image         sensor_msgs/Image 32FC1         ground-truth depth (m, NaN none)
/camera/pose                geometry_msgs/PoseStamped       camera-to-world, frame ``world``: the
                                                            source's samples spanning the frames
                                                            (0.5 s margin); from a ``/tf``
                                                            chain one per colour frame instead
==========================  ==============================  =====================================

A conversion writes into a hidden temporary folder next to the target and renames it into
place only when it completes, so an interrupted run never leaves a bag that looks complete.

The work lives in ``tum_to_bag`` (TUM folders), ``recorded_to_bag`` (ROS 1 bags and rosbag2s,
with ``recorded_poses`` and ``tf_tree``), ``pose_samples`` and ``bag_writer``; this module is
the front door and keeps the names other code imports from it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .bag_layout import BagTopics, ConvertResult, FrameIds
from .bag_recovery import readable_rosbag2
from .bag_writer import AtomicBagWriter
from .recorded_to_bag import recorded_to_rosbag2
from .tf_tree import TfTree
from .tum_to_bag import tum_to_rosbag

__all__ = [
    'AtomicBagWriter',
    'BagTopics',
    'ConvertResult',
    'FrameIds',
    'TfTree',
    'convert',
    'recorded_to_rosbag2',
    'tum_to_rosbag',
]

#: Options of ``recorded_to_rosbag2`` that mean nothing for a TUM folder.
RECORDED_ONLY = ('groundtruth', 'camera_yaml', 'source_topics', 'tf_world_frame', 'tf_camera_frame')


def convert(src: str | Path, out: str | Path, **options: Any) -> ConvertResult:
    """Convert a TUM folder, a ROS 1 ``.bag`` or a rosbag2 folder into a rosbag2 in our layout
    (options as the two functions).

    Options that only apply to recorded bags (``groundtruth``, ``camera_yaml``,
    ``source_topics``, ``tf_*``) are rejected for a TUM folder rather than silently ignored.
    """
    path = Path(src)
    if not path.exists():
        raise FileNotFoundError(f'source {path} not found')
    if path.is_dir() and (path / 'rgb.txt').is_file():
        given = [k for k in RECORDED_ONLY if options.get(k) is not None]
        if given:
            raise ValueError(
                f'{", ".join(given)} only apply to a ROS 1 bag or a rosbag2 source, not to TUM folder {path}'
            )
        return tum_to_rosbag(path, out, **{k: v for k, v in options.items() if k not in RECORDED_ONLY})
    if path.is_dir() and not readable_rosbag2(path):
        raise ValueError(f'{path} is neither a TUM folder (no rgb.txt) nor a rosbag2 (no metadata.yaml)')
    return recorded_to_rosbag2(path, out, **{k: v for k, v in options.items() if v is not None})
