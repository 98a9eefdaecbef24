"""``evaluate``: the focal length check on a loaded sequence, as ``multi_view_node`` runs it.

The check (``multiview/focal_check.py``) reads the sequence's first posed frames in stream
order. With ``focal_check.mode: correct`` and a camera the images and poses disagree with,
every method then runs on the corrected camera, as the node's keyframes downstream of the
multi-view node do; the ground truth keeps its own camera.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

from ..data.sequence import Sequence
from ..multiview.focal_bias import focal_uncertainty
from ..multiview.focal_check import FocalCheckConfig, FocalEstimate, check_frames
from .checks import run_check

log = logging.getLogger(__name__)

STAGE = 'focal_check'
#: The key of the check's outcome ``(estimate, corrected)`` in a sequence's shared memo
#: (``KeyframeContext.shared``), which the filter's published std reads (:func:`checked_uncertainty`).
SHARED_KEY = 'focal_check'


def check_focal(sequence: Sequence, params: dict) -> tuple[Sequence, FocalEstimate | None]:
    """The sequence to evaluate (its camera corrected when asked and needed) and the estimate
    (``None`` when the check is off or the sequence is too short to finish it)."""
    config, estimate = run_check(
        sequence,
        params,
        STAGE,
        FocalCheckConfig(),
        lambda seq, cfg: check_frames(seq.camera, seq.frames, cfg),
        'focal length',
    )
    if estimate is not None and estimate.applied(config.mode):
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


def checked_uncertainty(shared: dict[str, Any], prior: float) -> float:
    """``filter.focal_uncertainty`` as the sequence's focal length check left it
    (``focal_bias.focal_uncertainty``; ``prior`` when the check did not run or finish)."""
    estimate, corrected = shared.get(SHARED_KEY, (None, False))
    return focal_uncertainty(estimate, prior, corrected)
