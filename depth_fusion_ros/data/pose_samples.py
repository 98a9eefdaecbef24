"""The pose source's own samples that a converted bag carries, and their order among the frames.

A SLAM system or a motion capture publishes its poses at its own stamps (TUM's ground truth is
100 Hz mocap), and ``multi_view_node`` interpolates them itself, at the image stamps or, after
a time offset correction, a few tens of ms off them. A bag of poses already blended at the
image stamps would leave the node re-reading blends, so the converters write the source's
samples that span the written frames, with ``SPAN_MARGIN_NS`` either side for those reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from .bag_layout import POSE_STAMPED, BagTopics, FrameIds
from .messages import header_msg, pose_stamped_msg
from .tum import TumTrajectory

#: Samples written beyond the first and last frame (s): a node may read poses a few tens of ms
#: off the image stamps once it corrects a time offset; half a second leaves room to spare.
SPAN_MARGIN_NS = 500_000_000


def samples_spanning(
    trajectory: TumTrajectory, first_ns: int, last_ns: int, margin_ns: int = SPAN_MARGIN_NS
) -> TumTrajectory:
    """The samples from the last one at or before ``first_ns - margin_ns`` to the first one at or
    after ``last_ns + margin_ns`` (clipped to the trajectory: every sample when it is shorter)."""
    stamps = trajectory.stamps_ns
    if not len(stamps):
        return trajectory
    lo = max(int(np.searchsorted(stamps, first_ns - margin_ns, side='right')) - 1, 0)
    hi = min(int(np.searchsorted(stamps, last_ns + margin_ns, side='left')), len(stamps) - 1)
    return TumTrajectory(trajectory.path, stamps[lo : hi + 1], trajectory.poses[lo : hi + 1])


class SampleFeed:
    """A pose source's samples as PoseStamped messages, handed out in stamp order up to a stamp,
    so a converter can interleave them with the frames it writes (header stamp = bag time)."""

    def __init__(self, samples: TumTrajectory, topics: BagTopics, frame_ids: FrameIds, typestore: Any):
        self._stamps = samples.stamps_ns.tolist()
        self._poses = samples.poses
        self._next = 0
        self._topic = topics.pose
        self._frame = frame_ids.world
        self._typestore = typestore

    def until(self, stamp_ns: int | None = None) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, msgtype, stamp, msg)`` of the samples not yet handed out stamped at or
        before ``stamp_ns`` (all of them when ``None``)."""
        while self._next < len(self._stamps) and (stamp_ns is None or self._stamps[self._next] <= stamp_ns):
            stamp, T = self._stamps[self._next], self._poses[self._next]
            self._next += 1
            hdr = header_msg(stamp, self._frame, kind=self._typestore)
            yield self._topic, POSE_STAMPED, stamp, pose_stamped_msg(T, hdr, kind=self._typestore)
