"""Stage 3 of the point selection: local consistency of the multi-view points (an addition).

The paper's stage 1 keeps the best 25 % of the multi-view estimates by score and stage 2 keeps
the inliers of one global line ``m ≈ a·s + b`` (35 % band). What is left between that
selection and the oracle (the estimates whose ground-truth error is below 10 cm, paper
Table II right), measured on synthetic sequences with exact truth (docs/fusion.md):

* **the score is a weak predictor**: the stage-1 points are barely more often right than
  the whole semi-dense map (84-86 % against 75-80 % within 10 cm);
* **the band throws away the most useful points**: a correct estimate where the network is
  more than 35 % off is a stage-2 outlier by construction, yet it is exactly where the
  fusion has most to correct. On a synthetic keyframe the oracle restricted to the band gave
  0.276 m, the whole oracle 0.183 m (single view 0.423 m).

What separates a wrong match from a right one is that the single-view error is smooth by
regions and a wrong match is not: the log residual ``r = log(m / s)`` of a good estimate
agrees with the residuals of its neighbours, that of a wrong one jumps. Stage 3 tests every
multi-view estimate (a *candidate*) against a local reference: the Gaussian-weighted mean of
its neighbours' residuals (scale ``sigma_px``, the point itself excluded). The first pass
takes the neighbours among all candidates (wrong matches are the minority and are outvoted),
each further pass (``iterations``) among the points the previous one kept. A candidate is
kept when ``|r - reference| <= tolerance`` and its neighbours' Gaussian weight is at least
``min_support``; an untested (isolated) stage-2 point is kept, as the paper would. The
guard (``guard.py``) then judges the resulting points as it judged Ω.

Vectorised on torch (normalised convolution with a separable Gaussian): any device.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .gaussian import gaussian_kernel, gaussian_sum
from .selection import LinearFit, inliers_of

CANDIDATE_SCOPES = ('omega', 'band', 'all')
#: One line per ``ConsistencyConfig`` field (ROS parameter descriptions, docs).
CONSISTENCY_PARAMETER_DESCRIPTIONS: dict[str, str] = {
    'enabled': 'stage 3 (off: the paper selection): test the candidate multi-view estimates against '
    'their neighbours (drop inconsistent stage-2 points, add consistent ones stage 1 left out)',
    'sigma_px': 'stage 3: Gaussian scale (pixels) of the neighbourhood giving a point its local reference',
    'tolerance': 'stage 3: largest |log(m/s) - local reference| of a kept point',
    'min_support': 'stage 3: smallest Gaussian-weighted neighbour count for a point to be tested',
    'iterations': 'stage 3: passes; each takes its reference from the points the previous one kept',
    'candidates': "stage 3: estimates it may keep: 'omega' (only drop stage-2 points), 'band' (every "
    "estimate within the stage-2 threshold of the line), 'all'",
}


@dataclass(frozen=True)
class ConsistencyConfig:
    """Parameters of stage 3 (also the ``consistency.*`` ROS parameters).

    ``sigma_px``, ``tolerance`` and ``iterations`` were chosen on synthetic keyframes (320x240)
    only. Off by default: it raised the share of right points on every sequence but did not
    lower the fused error on TUM fr1_xyz or 7-Scenes, and raised it on three stress cases
    (docs/fusion.md, "Stage 3").
    """

    #: Off by default: on the real sequences it did not beat the paper's selection (docs/fusion.md).
    enabled: bool = False
    sigma_px: float = 3.0
    tolerance: float = 0.03
    min_support: float = 1.0
    iterations: int = 3
    #: Which estimates may be kept: ``omega`` (stage 3 only drops stage-2 points), ``band``
    #: (every estimate within the stage-2 threshold of the line), ``all``.
    candidates: str = 'band'

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        for name in ('sigma_px', 'tolerance'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f'consistency.{name} must be a positive number, got {value}')
        if not (np.isfinite(self.min_support) and self.min_support >= 0):
            raise ValueError(f'consistency.min_support must be >= 0, got {self.min_support}')
        if self.candidates not in CANDIDATE_SCOPES:
            raise ValueError(
                f'consistency.candidates must be one of {", ".join(CANDIDATE_SCOPES)}, '
                f'got {self.candidates!r}'
            )
        if int(self.iterations) < 1:
            raise ValueError(f'consistency.iterations must be >= 1, got {self.iterations}')


def local_reference(
    residual: torch.Tensor, reference: torch.Tensor, g: torch.Tensor, g0: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussian-weighted mean of ``residual`` over the ``reference`` pixels around each pixel,
    the pixel itself excluded, and the weight of those neighbours (their Gaussian count)."""
    ref = reference.to(residual.dtype)
    values = torch.where(reference, residual, torch.zeros_like(residual))
    centre = g0 * g0
    num = gaussian_sum(values, g) - centre * values
    den = gaussian_sum(ref, g) - centre * ref
    den = torch.clamp(den, min=0.0)
    mean = num / torch.clamp(den, min=1e-12)
    return mean, den


def consistent_points(
    s: np.ndarray,
    m: np.ndarray,
    omega: np.ndarray,
    candidates: np.ndarray,
    config: ConsistencyConfig,
    device: str = 'cpu',
) -> tuple[np.ndarray, dict[str, float]]:
    """Stage 3: the points to fuse, from the stage-2 points ``omega`` and the ``candidates``
    (every usable multi-view estimate). ``s``: the single-view depth in metres (aligned for a
    non-metric source); ``m``: the multi-view depth.

    The first pass takes its reference from every candidate (a wrong match is outvoted by
    its right neighbours), the next ones from the points the previous pass kept. Returns
    the mask and counts (``n_dropped`` stage-2 points, ``n_added`` other estimates).
    """
    dev = torch.device(device)
    with np.errstate(invalid='ignore', divide='ignore'):
        finite = np.isfinite(s) & np.isfinite(m) & (s > 0) & (m > 0)
        residual = np.where(finite, np.log(np.where(finite, m, 1.0)) - np.log(np.where(finite, s, 1.0)), 0.0)
    r = torch.from_numpy(residual.astype(np.float32)).to(dev)
    omega_t = torch.from_numpy(omega & finite).to(dev)
    cand_t = torch.from_numpy((candidates | omega) & finite).to(dev)
    g, g0 = gaussian_kernel(config.sigma_px, dev)
    reference = cand_t
    kept = omega_t
    for _ in range(int(config.iterations)):
        mean, support = local_reference(r, reference, g, g0)
        tested = support >= config.min_support
        agrees = torch.abs(r - mean) <= config.tolerance
        kept = cand_t & ((tested & agrees) | (omega_t & ~tested))
        reference = kept
    out = kept.cpu().numpy()
    n_omega = int(omega_t.sum())
    stats = {
        'n_candidates': float(cand_t.sum()),
        'n_dropped': float(n_omega - int((kept & omega_t).sum())),
        'n_added': float(int((kept & ~omega_t).sum())),
        'n_stage3': float(out.sum()),
    }
    return out, stats


def stage3_candidates(
    scope: str,
    omega: np.ndarray,
    usable: np.ndarray,
    s: np.ndarray,
    m: np.ndarray,
    fit: LinearFit,
    threshold: float,
    relative: bool,
) -> np.ndarray:
    """The estimates stage 3 may keep: ``omega`` (only drop), ``band`` (every usable estimate the
    stage-2 line explains within its inlier threshold, stage 1 or not), ``all`` (every usable one)."""
    if scope == 'omega':
        return omega
    if scope == 'band':
        band = np.zeros_like(usable)
        band[usable] = inliers_of(fit, s[usable], m[usable], threshold, relative)
        return band
    return usable
