"""``evaluate``: the time offset check on a loaded sequence, as ``multi_view_node`` runs it.

The check (``multiview/time_offset_check.py``) reads the sequence's posed frames in stream
order. With ``time_offset_check.mode: correct`` and poses the images disagree with in time,
every method then runs on the poses read at the fitted offset (interpolated between the
frames' own poses, :func:`~depth_fusion_ros.multiview.time_offset_check.shift_in_time`), as
the node reads its pose buffer at the corrected offset; the ground-truth depth is the
camera's own and does not move. It runs before the focal length check, which reads the poses.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..data.sequence import Sequence
from ..multiview.time_offset_check import (
    TimeOffsetCheckConfig,
    TimeOffsetEstimate,
    check_stream,
    shift_in_time,
)
from ..pose_curve import interpolate_poses_cubic
from .checks import run_check

log = logging.getLogger(__name__)

STAGE = 'time_offset_check'


def check_time_offset(sequence: Sequence, params: dict) -> tuple[Sequence, TimeOffsetEstimate | None]:
    """The sequence to evaluate (its poses re-read when asked and needed) and the estimate
    (``None`` when the check is off or the sequence is too short to finish it)."""
    config, estimate = run_check(
        sequence,
        params,
        STAGE,
        TimeOffsetCheckConfig(),
        lambda seq, cfg: check_stream(seq.camera, seq.frames, cfg),
        'time offset',
    )
    if estimate is not None and config.mode == 'correct' and estimate.verdict == 'disagrees':
        sequence = shifted_sequence(sequence, estimate.offset)
        log.warning(
            '%s: every method uses the poses %+.0f ms later (time_offset_check.mode correct)',
            sequence.name,
            estimate.offset * 1000,
        )
    return sequence, estimate


def shifted_sequence(sequence: Sequence, offset: float) -> Sequence:
    """``sequence`` with every frame's pose read ``offset`` seconds later: from the pose source as
    recorded (``Sequence.pose_stream``: its own samples, so a pose source stamped off by the
    offset gives its exact poses back), else from the frames' own poses; both along the cubic
    through them (``pose_curve.py``), a frame past either end of the record along the end step."""
    stamps = np.array([f.stamp for f in sequence.frames])
    poses = shift_in_time(stamps, sequence.poses, offset)
    if sequence.pose_stream is not None and len(sequence.pose_stream[0]) >= 2:
        source_stamps, source_poses = sequence.pose_stream
        t0 = float(source_stamps[0])
        read, inside = interpolate_poses_cubic(source_stamps - t0, source_poses, stamps + offset - t0)
        poses[inside] = read[inside]
    return sequence.with_poses(poses)


def estimate_json(estimate: TimeOffsetEstimate | None, corrected: bool) -> dict | None:
    """The ``time_offset_check`` entry of a sequence in results.json: the estimate's fields, the
    fitted ``pose_time_offset`` and whether every method ran on poses read at it. ``flat``
    says that the pairs fit every offset alike: the fitted one is then noise (often the
    search's edge), which the report must not print as an offset to copy."""
    if estimate is None:
        return None
    return {
        **dataclasses.asdict(estimate),
        'fitted_offset': estimate.fitted,
        'flat': estimate.flat,
        'corrected': corrected,
    }
