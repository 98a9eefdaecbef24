"""``evaluate``: the focal length check on a loaded sequence, as ``multi_view_node`` runs it.

The check (``multiview/focal_check.py``) reads the sequence's first posed frames in stream
order. With ``focal_check.mode: correct`` and a camera the images and poses disagree with,
every method then runs on the corrected camera, as the node's keyframes downstream of the
multi-view node do; the ground truth keeps its own camera. A lens distortion the check finds
is taken first, before the mount check (:func:`take_lens`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

from ..data.lens_correction import undistort_sequence
from ..data.sequence import Sequence
from ..multiview.focal_bias import focal_uncertainty
from ..multiview.focal_check import FocalCheckConfig, FocalEstimate, check_frames
from .checks import check_config, run_check

log = logging.getLogger(__name__)

STAGE = 'focal_check'
#: The key of the check's outcome ``(estimate, corrected)`` in a sequence's shared memo
#: (``KeyframeContext.shared``), which the filter's published std reads (:func:`checked_uncertainty`).
SHARED_KEY = 'focal_check'


def take_lens(sequence: Sequence, params: dict) -> tuple[Sequence, FocalEstimate | None, float]:
    """The focal length check's first look, before the mount check: the sequence (its images,
    and the ground truth with them, undistorted when a lens is taken), the estimate and the
    lens ``k1`` taken (0: none).

    As ``multi_view_node`` does in ``correct`` mode, a lens the check finds is taken first
    (``data/lens_correction.py``): read through it, the pairs can also fit a turned mount (2.1
    deg on the lens stress case of seed 5 at 240x180), and the node starts its mount and focal
    length checks over once it has the lens. :func:`check_focal` then checks the focal length
    on what the mount check leaves."""
    config, estimate = _run(sequence, params)
    if estimate is None or not estimate.lens_distorted or config.mode != 'correct':
        return sequence, estimate, 0.0
    k1 = estimate.lens.k1
    log.warning(
        '%s: images and ground truth undistorted with k1 %+.3f, focal length checked again '
        '(focal_check.mode correct)',
        sequence.name,
        k1,
    )
    return undistort_sequence(sequence, k1), estimate, k1


def check_focal(
    sequence: Sequence, params: dict, first: FocalEstimate | None, again: bool, after_lens: bool = False
) -> tuple[Sequence, FocalEstimate | None]:
    """The sequence to evaluate (its camera corrected when asked and needed) and the estimate
    (``None`` when the check is off or the sequence is too short to finish it).

    ``first``: :func:`take_lens`'s estimate, kept unless ``again`` (a lens was taken or the
    mount check turned the poses since): then the check runs on the sequence as it is now.
    ``after_lens``: the images were undistorted with a lens the check fitted; a focal
    disagreement is then not taken (``FocalEstimate.applied``)."""
    if again:
        config, estimate = _run(sequence, params)
    else:
        config, estimate = check_config(params, STAGE, FocalCheckConfig()), first
    if estimate is not None and estimate.applied(config.mode, after_lens):
        sequence = dataclasses.replace(sequence, camera=estimate.corrected(sequence.camera))
        log.warning('%s: every method uses fx %.1f px (focal_check.mode correct)', sequence.name, estimate.fx)
    return sequence, estimate


def _run(sequence: Sequence, params: dict) -> tuple[FocalCheckConfig, FocalEstimate | None]:
    return run_check(
        sequence,
        params,
        STAGE,
        FocalCheckConfig(),
        lambda seq, cfg: check_frames(seq.camera, seq.frames, cfg),
        'focal length',
    )


def estimate_json(estimate: FocalEstimate | None, corrected: bool, lens_k1: float = 0.0) -> dict | None:
    """The ``focal_check`` entry of a sequence in results.json: the estimate's fields, the fitted
    focal lengths, whether every method ran on them and the lens ``k1`` the images were
    undistorted with (0: none; the estimate is then the check on the undistorted images)."""
    if estimate is None:
        return None
    return {
        **dataclasses.asdict(estimate),
        'fitted_fx': estimate.fx,
        'fitted_fy': estimate.fy,
        'corrected': corrected,
        'lens_corrected_k1': lens_k1,
    }


def checked_uncertainty(shared: dict[str, Any], prior: float) -> float:
    """``filter.focal_uncertainty`` as the sequence's focal length check left it
    (``focal_bias.focal_uncertainty``; ``prior`` when the check did not run or finish)."""
    estimate, corrected = shared.get(SHARED_KEY, (None, False))
    return focal_uncertainty(estimate, prior, corrected)
