"""``evaluate``: the focal length check on a loaded sequence, as ``multi_view_node`` runs it.

The check (``multiview/focal_check.py``) reads the sequence's first posed frames in stream
order. With ``focal_check.mode: correct`` and a camera the images and poses disagree with,
every method then runs on the corrected camera, as the node's keyframes downstream of the
multi-view node do; the ground truth keeps its own camera.
"""

from __future__ import annotations

import dataclasses
import logging

from ..data.sequence import Sequence
from ..multiview.focal_check import FocalCheckConfig, FocalEstimate, check_frames
from ..multiview.params import apply_overrides

log = logging.getLogger(__name__)

STAGE = 'focal_check'


def check_focal(sequence: Sequence, params: dict) -> tuple[Sequence, FocalEstimate | None]:
    """The sequence to evaluate (its camera corrected when asked and needed) and the estimate
    (``None`` when the check is off or the sequence is too short to finish it)."""
    config = apply_overrides(FocalCheckConfig(), params.get(STAGE, {}), STAGE)
    if config.mode == 'off':
        return sequence, None
    check = check_frames(sequence.camera, sequence.frames, config)
    estimate = check.result
    if estimate is None:
        log.info(
            '%s: focal length not checked: %d image pairs in %d frames, %d needed',
            sequence.name,
            len(check.pairs),
            len(sequence.frames),
            config.pairs,
        )
        return sequence, None
    level = logging.WARNING if estimate.verdict == 'disagrees' else logging.INFO
    log.log(level, '%s: %s', sequence.name, estimate.message())
    if config.mode == 'correct' and estimate.verdict == 'disagrees':
        sequence = dataclasses.replace(sequence, camera=estimate.corrected(sequence.camera))
        log.warning('%s: every method uses fx %.1f px (focal_check.mode correct)', sequence.name, estimate.fx)
    return sequence, estimate


def estimate_json(estimate: FocalEstimate | None, corrected: bool) -> dict | None:
    """The ``focal_check`` entry of a sequence in results.json: the estimate's fields, the fitted
    focal lengths and whether every method ran on them."""
    if estimate is None:
        return None
    return {
        **dataclasses.asdict(estimate),
        'fitted_fx': estimate.fx,
        'fitted_fy': estimate.fy,
        'corrected': corrected,
    }
