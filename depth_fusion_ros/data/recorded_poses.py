"""Where a recorded bag's conversion (ROS 1 or rosbag2) takes its poses from, and which it writes.

Every source gives the poses at the colour stamps, which decide the frames that have one. What
goes into the bag differs: a groundtruth file or a PoseStamped topic is a pose source that
published its own samples, and those are written (the node interpolates them itself, also at a
corrected time offset); a ``/tf`` chain is only known where its edges are composed at common
stamps, so it writes one pose per colour frame, interpolated at its stamp.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .tf_tree import TfTree, frame_name
from .tum import TumTrajectory, read_groundtruth

logger = logging.getLogger(__name__)

OWN_SAMPLES = 'its own samples'
INTERPOLATED = 'interpolated at the colour stamps'


@dataclass(frozen=True)
class PoseSource:
    """Poses at the colour stamps (``at_frames``, ``valid``), and the source's own samples to
    write instead of them (``None``: write ``at_frames``)."""

    name: str
    at_frames: np.ndarray  # (M, 4, 4), NaN where not valid
    valid: np.ndarray  # (M,) bool
    samples: TumTrajectory | None

    @property
    def found(self) -> bool:
        return self.name != 'none'


def _own(name: str, trajectory: TumTrajectory, query: np.ndarray) -> PoseSource:
    T, ok = trajectory.interpolate(query)
    return PoseSource(f'{name}, {OWN_SAMPLES}', T, ok, trajectory)


def recorded_pose_source(
    query: np.ndarray,
    *,
    groundtruth: Path | None,
    pose_stamps: list[int],
    poses: list[np.ndarray],
    tf: TfTree,
    tf_world: str,
    tf_camera: str | None,
) -> PoseSource:
    """The best source available: the ``groundtruth`` file, else the pose topic's messages
    (``pose_stamps``, ``poses``), else the ``tf`` chain ``tf_world`` -> ``tf_camera``."""
    if groundtruth is not None:
        return _own(f'groundtruth ({groundtruth})', read_groundtruth(groundtruth), query)
    if pose_stamps:
        return _own('pose topic', TumTrajectory.from_samples('pose topic', pose_stamps, poses), query)
    if tf_camera and tf.frames:
        T, ok = tf.lookup(tf_world, tf_camera, query)
        name = f'/tf ({frame_name(tf_world)} -> {frame_name(tf_camera)}), {INTERPOLATED}'
        return PoseSource(name, T, ok, None)
    logger.warning('no ground truth, pose topic or /tf in the bag: writing no poses')
    return PoseSource('none', np.full((len(query), 4, 4), np.nan), np.zeros(len(query), bool), None)
