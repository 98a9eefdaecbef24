"""How far an uncertain focal length can bias the multi-view depth, per pixel.

Why: a focal length a few per cent off barely moves a depth triangulated from a sideways
baseline, but under rotation-dominant motion (a handheld sweep, a robot turning on the spot)
the told rotation is undone with the wrong focal length, and what is left slides every point
along its epipolar line like parallax. The depths are then all biased the same way (an
inverse-depth offset), they agree with each other, and the fusion's guard trusted them: a
rotation sweep with camera_info 5 % long, the focal check unable to pin it (rolling shutter,
exposure and pose noise together), was fused 46 % above its own single view (docs/fusion.md,
"An unverified focal length under rotation"). The images cannot tell this bias apart from
depth, so what can be said is its size: for each frame that updated the filter's keyframe (or,
with the estimates carried into it, the keyframes before it), the shift along the epipolar
line that a focal change of ``eps`` gives the point, over the line's motion per unit inverse
depth; combined with the filter's own weights (``j^2``), as its posterior mean combines the
frames. The filter adds it to the published depth std, so the guard (``guard.max_relative_std``,
``guard.min_precise_fraction``) and the fusion's precision weights see it.

``eps`` is what the focal length check has verified (:func:`focal_uncertainty`): its standard
error once it has read the stream, ``filter.focal_uncertainty`` before then or when it cannot
tell.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from .cost_volume import epipolar_matrices, epipolar_motion

if TYPE_CHECKING:
    from .focal_check import FocalEstimate

#: The focal change the bias is computed for (relative); the result is per unit of it.
STEP = 0.01
#: The largest focal uncertainty a check's standard error is taken for (an unobservable fit
#: may report any standard error; 25 % already leaves no rotation-dominant estimate trusted).
MAX_UNCERTAINTY = 0.25
#: At most this many of the frames that updated a keyframe enter the bias (evenly spaced):
#: it is computed once per published keyframe, and neighbouring frames add little.
MAX_FRAMES = 4
#: The frames a keyframe's bias is read from: the last this many that updated it or, carried
#: with their estimates into it, the keyframes before it.
KEPT_FRAMES = 16


#: Standard errors of an early look's fit its bound adds to its offset (:func:`focal_uncertainty`).
EARLY_STDERRS = 2.0


def focal_uncertainty(
    estimate: FocalEstimate | None,
    prior: float,
    corrected: bool,
    early: FocalEstimate | None = None,
) -> float:
    """The relative focal length uncertainty the multi-view depth is published with.

    ``estimate``: the focal length check's result, ``None`` while it has not read enough of
    the stream; ``corrected``: whether the multi-view depth runs on its fitted focal length
    (``FocalEstimate.applied``). A verified focal length (``consistent``, or ``disagrees`` and
    corrected) is good to the fit's standard error; one the check found off but kept
    (``suspect``, or ``disagrees`` in warn mode) is off by the fit as well; one it cannot
    pin down (``unobservable``) is at least as uncertain as ``prior`` and as its own fit.
    One standard error, not two: the guard weighs the bias against the single view's own
    error (``guard.max_relative_std``, ``guard.single_error_share``), and at two (when the
    share was 1) a causal 500-frame read of 7-Scenes
    (verified to 1.8 %) lost 1.5 % of its fused MAE on a stretch where the camera turns.

    ``early``: before the check has read the stream, the estimate of its early look
    (``FocalCheck.early``, at ``lens_early_pairs``) when that already agreed (``consistent``).
    It bounds the focal error by its offset plus two standard errors, more carefully than a
    final verdict's one, and replaces the prior where it is smaller: a rotation sweep is
    then trusted from about frame 33 instead of 49. On the 38 streams of the stress cases
    at seeds 151 and 152, every early look that agreed was on an exact focal length, and
    every stream with a wrong one (5 or 10 %) was ``unobservable`` or ``disagrees`` at 6, 8
    and 12 pairs (docs/multi_view.md, "An early agreement").

    A result whose pairs fit a lens distortion better (``lens_distorted``) verified nothing of
    the images the depth comes from: until the node has taken the lens and the check has read
    the undistorted stream again (it starts over then), they carry the lens's error, which no
    focal length removes. The uncertainty is then never below ``prior``: a keyframe filtered on
    the distorted images and published after the result was trusted at the fit's 2 % and fused
    at 1.19x its input (``lens_distortion`` seed 241, docs/fusion.md "A lens found while a
    keyframe is on its way"); a lens that is not taken (``focal_check.mode`` warn, a fisheye
    model) is the same for the whole stream.
    """
    if prior == 0.0:
        return 0.0
    if estimate is not None and estimate.lens_distorted:
        return max(prior, _verified(estimate, prior, corrected))
    if estimate is None:
        if early is None or early.verdict != 'consistent' or not math.isfinite(early.stderr):
            return prior
        return min(prior, abs(math.log(max(early.scale, 1e-6))) + EARLY_STDERRS * early.stderr)
    return _verified(estimate, prior, corrected)


def _verified(estimate: FocalEstimate, prior: float, corrected: bool) -> float:
    """What the check's result says of the focal length the depth runs on (see above)."""
    spread = estimate.stderr if math.isfinite(estimate.stderr) else MAX_UNCERTAINTY
    verdict = estimate.verdict
    if verdict == 'unobservable':
        eps = max(prior, spread)
    elif verdict == 'consistent' or (verdict == 'disagrees' and corrected):
        eps = spread
    else:
        eps = abs(math.log(max(estimate.scale, 1e-6))) + spread
    return min(eps, MAX_UNCERTAINTY)


def remember_update(poses: list[np.ndarray], pose: np.ndarray) -> None:
    """Append the pose of a frame that updated the keyframe, keeping the last ``KEPT_FRAMES``."""
    poses.append(pose)
    del poses[:-KEPT_FRAMES]


def spaced(poses: Sequence[np.ndarray], n: int = MAX_FRAMES) -> list[np.ndarray]:
    """At most ``n`` of ``poses``, evenly spaced, the last one included."""
    if len(poses) <= n:
        return list(poses)
    pick = np.linspace(0, len(poses) - 1, n).round().astype(int)
    return [poses[i] for i in pick]


def inverse_depth_bias(
    K: np.ndarray, us: torch.Tensor, vs: torch.Tensor, rho: torch.Tensor, poses_fk: Sequence[np.ndarray]
) -> torch.Tensor:
    """Inverse-depth bias (R,) per unit relative focal error of the estimates at keyframe pixels
    ``(us, vs)`` with inverse depths ``rho``, updated by frames at ``poses_fk`` (each the
    keyframe-to-frame transform ``T_fk``); 0 where no frame moved a point along a line.

    Per frame: the point's projection ``(a + rho b) / (a_2 + rho b_2)`` with ``a = K R K^-1 x``
    (``cost_volume.epipolar_matrices``), and again with both focal lengths ``1 + STEP`` times
    as long in the homography (only there: the translation's share of a focal error is a depth
    scale of that size, not this bias). The shift between the two along the line's motion ``m``
    (``cost_volume.epipolar_motion``, pixels per unit inverse depth), over ``|m|``, is the
    frame's bias, and the frames combine weighted by ``|m|^2`` as in the filter's update:
    ``sum(shift . m) / sum(|m|^2)``.
    """
    if len(poses_fk) == 0:
        return torch.zeros_like(rho)
    K = np.asarray(K, dtype=np.float64)
    scaled = K.copy()
    scaled[0, 0] *= 1.0 + STEP
    scaled[1, 1] *= 1.0 + STEP
    poses = np.stack(poses_fk)
    H, b = epipolar_matrices(K, poses, rho.device)  # (n, 3, 3), (n, 3)
    H_long, _ = epipolar_matrices(scaled, poses, rho.device)
    r = rho.to(H.dtype)
    x = torch.stack((us.to(H.dtype), vs.to(H.dtype), torch.ones_like(r)))
    num, den = torch.zeros_like(r), torch.zeros_like(r)
    # One frame at a time: its (R,) rows stay in cache (a batch of frames took twice as long).
    for f, (b0, b1, b2) in enumerate(b.tolist()):
        told, longer = H[f] @ x, H_long[f] @ x
        du, dv = epipolar_motion(told.unbind(0), (b0, b1, b2), r)
        w, w_long = told[2] + r * b2, longer[2] + r * b2
        rb0, rb1 = r * b0, r * b1
        shift_u = (longer[0] + rb0) / w_long - (told[0] + rb0) / w
        shift_v = (longer[1] + rb1) / w_long - (told[1] + rb1) / w
        num += shift_u * du + shift_v * dv
        den += du * du + dv * dv
    return (num.abs() / den.clamp(min=1e-12)).div_(STEP).to(rho.dtype)
