"""``evaluate``: the mount check on a loaded sequence, as ``multi_view_node`` runs it.

The check (``multiview/mount_check.py``) reads the sequence's posed frames in stream order,
after the time offset check (which may re-read the poses) and before the focal length check.
With ``mount_check.mode: correct`` and poses the images disagree with, every frame's pose
(and the pose source's record, ``Sequence.pose_stream``) is turned by the fitted rotation
(``T @ M``), as the node turns the poses it reads from then on; the ground-truth depth is the
camera's own and does not move. Poses that fit the images inverted (``pose_inversion.py``)
are said as a warning and used as told.
"""

from __future__ import annotations

import dataclasses
import logging

from ..data.sequence import Sequence
from ..multiview.mount_check import MountCheckConfig, MountEstimate, check_frames, turned
from .checks import run_check

log = logging.getLogger(__name__)

STAGE = 'mount_check'


def check_mount(sequence: Sequence, params: dict) -> tuple[Sequence, MountEstimate | None]:
    """The sequence to evaluate (its poses turned when asked and needed) and the estimate
    (``None`` when the check is off or the sequence is too short to finish it)."""
    config, estimate = run_check(
        sequence,
        params,
        STAGE,
        MountCheckConfig(),
        lambda seq, cfg: check_frames(seq.camera, seq.frames, cfg),
        'mount rotation',
    )
    if estimate is not None and config.mode == 'correct' and estimate.verdict == 'disagrees':
        sequence = turned_sequence(sequence, estimate)
        log.warning(
            '%s: every method uses the poses turned by %.2f deg (mount_check.mode correct)',
            sequence.name,
            estimate.angle_deg,
        )
    if estimate is not None and estimate.verdict == 'inverted':
        log.warning(
            '%s: %s; every method uses the poses as told (write the camera poses, T_wc, in the '
            'recording: multi_view_node withholds its multi-view depth for such poses)',
            sequence.name,
            estimate.message(),
        )
    return sequence, estimate


def turned_sequence(sequence: Sequence, estimate: MountEstimate) -> Sequence:
    """``sequence`` with every frame's pose and the pose source's record turned by the estimate."""
    stream = sequence.pose_stream
    if stream is not None:
        stream = (stream[0], turned(stream[1], estimate))
    return sequence.with_poses(turned(sequence.poses, estimate), stream)


def estimate_json(estimate: MountEstimate | None, corrected: bool) -> dict | None:
    """The ``mount_check`` entry of a sequence in results.json: the estimate's fields, the
    correction's angle and whether every method ran on the turned poses."""
    if estimate is None:
        return None
    return {**dataclasses.asdict(estimate), 'angle_deg': estimate.angle_deg, 'corrected': corrected}
