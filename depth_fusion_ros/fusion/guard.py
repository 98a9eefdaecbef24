"""The fusion's guard: never make the depth worse than the single-view input it started from.

The paper's fusion trusts every point of Ω: each bends the single-view depth ``s`` onto its
multi-view depth ``m``. Where the multi-view evidence is wrong (rotation-dominant motion,
wide baselines, weak texture, a wrong calibration) that makes the fused depth *worse* than
``s``. Stage 2 (one RANSAC line over the whole image with a loose threshold) cannot see it:
its threshold must pass the single-view error of correct points, which is as large as the
error of many wrong matches.

What separates the two errors is their *spatial structure*. A single-view network is wrong
smoothly, by regions (a segment off by 20 %), so the residual ``log m - log s`` of correct
points varies slowly across the image. Wrong matches are independent from point to point.
The guard therefore measures, per keyframe and without ground truth:

* **local consistency**: each point's log residual against the median of its Ω neighbours
  within ``neighbourhood_px`` (the nearest ``max_neighbours`` of them). The deviation
  estimates the multi-view noise alone (the smooth single-view error cancels); ``mv_noise``
  is its robust spread (MAD x 1.4826), and a point deviating by more than
  ``local_tolerance`` is *inconsistent*. The fusion averages about
  the points of a neighbourhood, so the noise that reaches the depth is
  ``effective_noise = mv_noise / sqrt(neighbours + 1)``; per-point fusion pays only while it is
  below ``max_mv_noise`` and below the single-view error ``sqrt(fit_spread² - mv_noise²)``.
  That average assumes independent errors; points whose own ``mv_noise`` is above
  ``max_point_noise`` come from geometry too weak for it (their errors shared as well as
  scattered), and the keyframe keeps its single view, their scale included;
* **support**: stage-2 inliers (``n_omega``) and their share of the stage-1 points
  (``inlier_ratio``); points with no Ω neighbour cannot be checked and are not trusted;
* **parallax** (when the multi-view result is known): each point's relative depth
  uncertainty ``depth_std / depth`` from one pixel of matching error, i.e. its parallax and
  epipolar geometry;
* **agreement between neighbours** (when the multi-view stage provides it): the fraction of
  the neighbour frames that individually confirm the match;
* **fit residual**: the robust spread of the log residual over Ω (``fit_spread``), which
  bounds how much the multi-view scale can be trusted.
* **shared bias** (when the multi-view stage provides it): the part of the points' relative
  std they all have in common (``shared_std``, the median over the trusted points of the
  filter's focal length bias); the pipeline then takes only the share of their global scale
  that it leaves them against the single view (``shared_scale.py``, ``shared_scale``);

and steps down a ladder (``DECISIONS``, least to most degraded):

=================  ======================================================================
``full``           the paper's fusion over Ω (almost every point is consistent)
``fewer_points``   the fusion over the trusted points only (consistent, enough parallax)
``scale_only``     no per-point bending: a smooth multiplicative correction of ``s`` from
                   the trusted points (W1 only, ``scale_sigma_px``): regional scale only
``single_scaled``  the single-view depth with the multi-view global scale (one number)
``single_view``    the single-view depth as it is (a non-metric source still needs the
                   fit to be in metres), flagged; confidence 0
=================  ======================================================================

In ``full`` and ``fewer_points`` the corrections fade back to ``s`` with the distance to
their points (``reach``, ``guard_apply.limit_reach``): a point speaks for its neighbourhood,
not for a flat region 100 px away whose single-view error is another region's. No decision
takes a scale from points the evidence rejected: with fewer than ``min_scale_points`` trusted
points the keyframe is ``single_view`` (low-parallax points agree with each other and are
biased together, so their small scatter says nothing about their scale).

Each decision comes with a reason (which evidence failed) and a keyframe confidence in
[0, 1] that multiplies the per-pixel confidence, so a consumer thresholding the confidence
drops the pixels of untrusted keyframes. No ground truth is used anywhere. The thresholds
were chosen on the synthetic stress cases (``data.synthetic.stress``), never on real data:
see docs/fusion.md.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field

import numpy as np

from .neighbour_median import nearest_median
from .subsample import seeded_subsample

log = logging.getLogger(__name__)

DECISIONS = ('full', 'fewer_points', 'scale_only', 'single_scaled', 'single_view')
#: Keyframe confidence of each decision before it is scaled by the share of trusted points.
DECISION_CONFIDENCE = {
    'full': 1.0,
    'fewer_points': 1.0,
    'scale_only': 0.5,
    'single_scaled': 0.2,
    'single_view': 0.0,
}
#: MAD -> standard deviation of a normal distribution.
MAD_TO_SIGMA = 1.4826

#: One line per ``GuardConfig`` field (ROS parameter descriptions, docs).
GUARD_PARAMETER_DESCRIPTIONS: dict[str, str] = {
    'neighbourhood_px': 'radius (px) of the Ω neighbourhood a point is checked against',
    'min_neighbours': 'Ω neighbours within the radius a point needs to be checked (else it is not trusted)',
    'max_neighbours': 'the median a point is checked against is over its nearest this many Ω neighbours '
    "within the radius (bounds the cost at the filter's dense points)",
    'local_tolerance': 'a point whose log residual deviates from its neighbours by more is inconsistent',
    'max_relative_std': "points whose depth_std / depth (1 px of matching error, and the filter's "
    "focal length bias) is above this and above single_error_share of the single view's own error: untrusted",
    'single_error_share': 'a point whose depth_std / depth is above max_relative_std is still trusted below '
    "this share of the single view's own error: points about as far off as the single view made it worse "
    '(docs/fusion.md); 0: never',
    'min_precise_fraction': 'when a smaller share of the points passes max_relative_std, none is trusted: '
    'the few that pass are the tail of an error the rest share (an unverified focal length under rotation)',
    'min_agreement': 'points confirmed by a smaller fraction of the neighbour frames are untrusted',
    'max_mv_noise': 'averaged multi-view noise (log depth) above which no point bends the depth',
    'max_point_noise': 'multi-view noise of one point (log depth, mv_noise) above which neither the points '
    'nor their scale are trusted: geometry that weak shares its errors (docs/fusion.md)',
    'full_fraction': 'share of Ω that must be trusted to fuse every point (else only the trusted ones)',
    'min_trusted_points': 'fewer trusted points than this: no per-point fusion',
    'min_scale_points': 'fewer trusted points than this: no regional or global scale correction',
    'min_inlier_ratio': 'stage-2 support: when stage 2 keeps a smaller share of the stage-1 points, '
    'they disagree more than they agree and the keyframe keeps its single-view depth',
    'scale_sigma_px': 'scale_only: proximity scale (px) of the smooth scale correction',
    'reach': 'local corrections fade towards the single-view depth with the distance D to their points: '
    'weight exp(-(D / (reach x image width))^2); 0: off',
    'max_scale_error': 'largest standard error (log) of the global multi-view scale that is still applied',
    'shared_scale': "weigh the points' global scale against the single view's when part of their std is "
    'common to all of them (an unverified focal length under rotation): the share n^2 / (n^2 + b^2) of it '
    "is taken, b the shared std, n^2 the larger of the single view's squared error and the squared "
    'disagreement less b^2 (fusion/shared_scale.py); false: all of it',
}


@dataclass(frozen=True)
class GuardConfig:
    """Thresholds of the guard (also the ``guard.*`` ROS parameters; ``FusionConfig.guard``
    switches it on and off).

    Defaults chosen on the synthetic stress cases at 160x120 and 320x240 (docs/fusion.md).
    """

    neighbourhood_px: float = 12.0
    min_neighbours: int = 2
    max_neighbours: int = 16
    local_tolerance: float = 0.15
    max_relative_std: float = 0.15
    single_error_share: float = 0.5
    min_precise_fraction: float = 0.2
    min_agreement: float = 0.5
    max_mv_noise: float = 0.06
    max_point_noise: float = 0.06
    full_fraction: float = 0.5
    min_trusted_points: int = 40
    min_scale_points: int = 20
    min_inlier_ratio: float = 0.5
    scale_sigma_px: float = 60.0
    reach: float = 0.3
    max_scale_error: float = 0.03
    shared_scale: bool = True

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        positive = (
            'neighbourhood_px',
            'local_tolerance',
            'max_relative_std',
            'max_mv_noise',
            'max_point_noise',
            'scale_sigma_px',
        )
        for name in positive:
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f'guard.{name} must be a positive number, got {getattr(self, name)}')
        for name in (
            'min_agreement',
            'full_fraction',
            'min_inlier_ratio',
            'min_precise_fraction',
            'single_error_share',
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f'guard.{name} must be in [0, 1], got {getattr(self, name)}')
        for name in ('min_neighbours', 'max_neighbours', 'min_trusted_points', 'min_scale_points'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'guard.{name} must be >= 1, got {getattr(self, name)}')
        if not (np.isfinite(self.reach) and self.reach >= 0):
            raise ValueError(f'guard.reach must be >= 0 (share of the image width; 0: off), got {self.reach}')
        if not (np.isfinite(self.max_scale_error) and self.max_scale_error >= 0):
            raise ValueError(f'guard.max_scale_error must be >= 0, got {self.max_scale_error}')


@dataclass
class MultiViewEvidence:
    """Optional per-pixel evidence of the multi-view stage (HxW float32, NaN = none).

    ``relative_std``: ``depth_std / depth`` (parallax and epipolar geometry of the estimate);
    ``agreement``: fraction of neighbour frames that confirm the match on their own;
    ``shared_relative_std``: the part of ``relative_std`` every estimate has in common (the
    bias of an unverified focal length under this motion, ``FilterResult.bias_std``).
    """

    relative_std: np.ndarray | None = None
    agreement: np.ndarray | None = None
    shared_relative_std: np.ndarray | None = None

    @classmethod
    def from_depth_std(
        cls,
        depth: np.ndarray | None,
        std: np.ndarray | None,
        agreement: np.ndarray | None = None,
        bias_std: np.ndarray | None = None,
    ) -> MultiViewEvidence:
        """From the multi-view depth, its standard deviation (either None: no parallax evidence)
        and the shared part of it (``bias_std``, m; None: unknown)."""
        known = depth is not None
        rel = relative_std(depth, std) if known and std is not None else None
        shared = relative_std(depth, bias_std) if known and bias_std is not None else None
        return cls(relative_std=rel, agreement=agreement, shared_relative_std=shared)

    @classmethod
    def from_result(cls, result: object) -> MultiViewEvidence:
        """From a ``MultiViewResult`` (or anything with ``depth``/``depth_std``, optional
        ``agreement`` and ``bias_std``)."""
        depth, std = getattr(result, 'depth', None), getattr(result, 'depth_std', None)
        agreement, bias = getattr(result, 'agreement', None), getattr(result, 'bias_std', None)
        return cls.from_depth_std(depth, std, agreement, bias)


@dataclass
class GuardVerdict:
    """The guard's decision for one keyframe."""

    decision: str
    reason: str
    #: Points the fusion may use (a subset of Ω); empty for the non-fusing decisions.
    trusted: np.ndarray
    #: Keyframe confidence in [0, 1]: multiplies the per-pixel confidence.
    confidence: float
    #: Global multi-view scale (median ratio m / s over the trusted points, or Ω).
    scale: float = 1.0
    evidence: dict[str, float] = field(default_factory=dict)

    @property
    def level(self) -> int:
        return DECISIONS.index(self.decision)


#: Points whose neighbour count is measured for the support (a strided subsample beyond):
#: the median count of 4096 points is the median of all of them to within a neighbour or two.
SUPPORT_SAMPLE = 4096


def _local_deviation(
    cols: np.ndarray,
    rows: np.ndarray,
    residual: np.ndarray,
    radius: float,
    min_neighbours: int,
    max_neighbours: int,
    device: str = 'cpu',
) -> tuple[np.ndarray, float]:
    """|residual - median residual of its nearest ``max_neighbours`` other points within
    ``radius``| per point (NaN when fewer than ``min_neighbours`` neighbours), and the median
    number of neighbours within ``radius`` (all of them, not capped: the support).

    ``cols``, ``rows``: Ω's distinct pixels in row-major order. Capping the neighbours bounds
    the cost (the temporal filter sends 6-40k points per keyframe, 150 neighbours each within
    12 px) and keeps the median local; equidistant neighbours count in a fixed order
    (``neighbour_median.py``), the same on the CPU and on a GPU.
    """
    n = len(cols)
    out = np.full(n, np.nan)
    if n == 0:
        return out, 0.0
    step = max(1, -(-n // SUPPORT_SAMPLE))
    middle, count, within = nearest_median(cols, rows, residual, radius, max_neighbours, device, step)
    checked = count >= max(min_neighbours, 1)
    out[checked] = np.abs(residual[checked] - middle[checked])
    return out, float(np.median(within))


def relative_std(depth: np.ndarray, std: np.ndarray) -> np.ndarray:
    """``std / depth`` in float32 (NaN where either is unknown): the precision the guard and the
    adaptation's choice of keyframes test with :func:`within_relative_std`."""
    with np.errstate(invalid='ignore', divide='ignore'):
        return (np.asarray(std, dtype=np.float32) / np.asarray(depth, dtype=np.float32)).astype(np.float32)


def within_relative_std(rel: np.ndarray, limit: float) -> np.ndarray:
    """Which estimates have ``depth_std / depth`` at most ``limit``; an unknown (NaN) one is not.
    The guard's precision test, shared with the adaptation's choice of keyframes
    (``adaptation/sample.py``), so that it trains only where the fusion would trust."""
    return np.nan_to_num(rel, nan=np.inf) <= limit


def assess(
    base: np.ndarray,
    m: np.ndarray,
    omega: np.ndarray,
    n_stage1: int,
    config: GuardConfig | None = None,
    evidence: MultiViewEvidence | None = None,
    *,
    sample: int | None = None,
    seed: int = 0,
    device: str = 'cpu',
) -> GuardVerdict:
    """Judge the multi-view evidence of one keyframe (all maps HxW on the working grid).

    ``base``: the single-view depth the fusion starts from (metres); ``m``: multi-view depth;
    ``omega``: the stage-2 points; ``n_stage1``: how many stage-1 points stage 2 saw.
    ``sample``: check at most this many points of Ω, a seeded uniform subsample (the fusion
    node fuses only ``max_points`` anyway; the local test's cost follows the points checked).
    Counts then stand for all of Ω: the trusted count and the neighbour support are scaled
    by ``|Ω| / sample``, the inlier ratio is Ω's own, and ``fewer_points`` trusts points of
    the sample only. ``device``: where the local test's neighbour search runs (the fusion's).
    """
    config = config or GuardConfig()
    with np.errstate(invalid='ignore'):
        usable = omega & np.isfinite(base) & np.isfinite(m) & (base > 0) & (m > 0)
    n_omega = int(usable.sum())
    stats: dict[str, float] = {'n_omega': float(n_omega), 'inlier_ratio': n_omega / max(n_stage1, 1)}
    empty = np.zeros(omega.shape, dtype=bool)
    if n_omega < config.min_scale_points:
        return GuardVerdict('single_view', f'only {n_omega} stage-2 points', empty, 0.0, 1.0, stats)

    rows, cols = np.nonzero(usable)
    if sample is not None and n_omega > sample:
        pick = seeded_subsample(n_omega, sample, seed)
        rows, cols = rows[pick], cols[pick]
    n_checked = len(rows)
    thin = n_omega / n_checked  # each checked point stands for this many points of Ω
    stats['n_checked'] = float(n_checked)
    residual = np.log(m[rows, cols].astype(np.float64)) - np.log(base[rows, cols].astype(np.float64))
    deviation, support = _local_deviation(
        cols, rows, residual, config.neighbourhood_px, config.min_neighbours, config.max_neighbours, device
    )
    support *= thin
    checked = np.isfinite(deviation)
    good = checked & (deviation <= config.local_tolerance)
    mv_noise = MAD_TO_SIGMA * float(np.median(deviation[checked])) / np.sqrt(2.0) if checked.any() else np.inf
    centre = float(np.median(residual))
    fit_spread = MAD_TO_SIGMA * float(np.median(np.abs(residual - centre)))
    # The fusion averages the points near a pixel, so what reaches the depth is the noise over
    # about ``support + 1`` points; it helps only while that is below the single-view error,
    # which is what remains of the fit residual's spread once the multi-view noise is removed.
    effective_noise = mv_noise / np.sqrt(support + 1.0)
    single_error = float(np.sqrt(max(fit_spread**2 - mv_noise**2, 0.0)))
    if evidence is not None and evidence.relative_std is not None:
        rel = evidence.relative_std[rows, cols]
        stats['median_relative_std'] = float(np.nanmedian(rel)) if np.isfinite(rel).any() else float('nan')
        # A point may be as far off as its std says and still help a single view that is
        # further off (a focal length verified to 2-4 % under rotation: docs/fusion.md); only
        # by a margin. ``single_error`` is read from the fit's spread, which cannot tell the
        # single view's error from the points' own, and trusted up to the whole of it the points
        # fused two hand-held streams (seed 71) to 1.003x and 1.02x their input.
        limit = max(config.max_relative_std, config.single_error_share * single_error)
        precise = within_relative_std(rel, limit)
        stats['precise_fraction'] = float(precise.mean())
        if stats['precise_fraction'] < config.min_precise_fraction:
            # The std says how far an estimate may be off, and a shared cause (the focal length
            # under rotation, multiview/focal_bias.py) puts most of them past the limit: the few
            # that pass are its tail, with the same error (a handheld stream's keyframe: 23
            # such points gave it the points' wrong scale, 1.45x its single view's MAE).
            precise[:] = False
        good &= precise
    if evidence is not None and evidence.agreement is not None:
        agree = evidence.agreement[rows, cols]
        stats['median_agreement'] = float(np.nanmedian(agree)) if np.isfinite(agree).any() else float('nan')
        good &= np.nan_to_num(agree, nan=0.0) >= config.min_agreement
    if evidence is not None and evidence.shared_relative_std is not None:
        shared = np.nan_to_num(evidence.shared_relative_std[rows, cols], nan=0.0)
        stats['shared_std'] = float(np.median(shared[good] if good.any() else shared))
    n_trusted = round(int(good.sum()) * thin)  # of all Ω
    trusted = np.zeros(omega.shape, dtype=bool)
    trusted[rows[good], cols[good]] = True
    trusted_fraction = float(good.mean())
    scale_points = residual[good] if n_trusted >= config.min_scale_points else residual
    scale_log = float(np.median(scale_points))
    scale_error = fit_spread / np.sqrt(max(len(scale_points), 1))
    stats.update(
        mv_noise=float(mv_noise),
        effective_noise=float(effective_noise),
        single_error=single_error,
        fit_spread=fit_spread,
        n_trusted=float(n_trusted),
        trusted_fraction=trusted_fraction,
        scale=float(np.exp(scale_log)),
        scale_error=float(scale_error),
    )
    scale = float(np.exp(scale_log))

    def verdict(decision: str, reason: str, points: np.ndarray) -> GuardVerdict:
        confidence = DECISION_CONFIDENCE[decision] * (trusted_fraction if decision != 'full' else 1.0)
        return GuardVerdict(decision, reason, points, float(confidence), scale, stats)

    if stats['inlier_ratio'] < config.min_inlier_ratio:
        # The stage-1 points are estimates the multi-view stage already accepted; when the
        # single <-> multi fit explains fewer than half of them, the rest are not noise around
        # it but a second story (measured: 0.80-0.91 on every good stress case and 0.78-0.87
        # on average on the real sequences, 0.30-0.34 where the filter's rotation-only
        # estimates were 59 % off). Neither the points nor their scale can be trusted.
        reason = f'stage 2 kept {n_omega} of {n_stage1} stage-1 points (< {config.min_inlier_ratio:g})'
        return verdict('single_view', reason, empty)
    if mv_noise > config.max_point_noise:
        # Points this noisy come from weak geometry (parallax small against the rotation and the
        # calibration's error), whose errors are shared as well as scattered: on SLAM keyframe
        # streams with a 5 % focal error, keyframes with a point noise of 0.07-0.09 gave scales
        # up to 40 % off, and fused up to 1.8x their input (docs/fusion.md).
        reason = (
            f'multi-view point noise {mv_noise:.3f} > {config.max_point_noise:g}: '
            'points and their scale untrusted'
        )
        return verdict('single_view', reason, empty)
    noisy = effective_noise > min(config.max_mv_noise, single_error)
    if not noisy and n_trusted >= config.min_trusted_points:
        if trusted_fraction >= config.full_fraction:
            return verdict('full', 'consistent multi-view points', usable.copy())
        return verdict(
            'fewer_points',
            f'{n_omega - n_trusted} of {n_omega} points inconsistent with their neighbours',
            trusted,
        )
    why = (
        f'averaged multi-view noise {effective_noise:.3f} > '
        f'min({config.max_mv_noise:g}, single-view {single_error:.3f})'
        if noisy
        else f'{n_trusted} trusted points < {config.min_trusted_points}'
    )
    if n_trusted >= config.min_scale_points and not noisy:
        return verdict('scale_only', why, trusted)
    if n_trusted < config.min_scale_points:
        # The scale would come from the points the evidence rejected. Their errors are not
        # independent (rotation-dominant motion biases every low-parallax depth the same
        # way: 15-25 % too near on the stress cases), so their small scatter says nothing.
        return verdict('single_view', why + f'; scale untrusted ({n_trusted} trusted points)', empty)
    if scale_error <= config.max_scale_error:
        return verdict('single_scaled', why + '; global scale kept', empty)
    return verdict('single_view', why + f'; scale uncertain ({scale_error:.3f})', empty)


def verdict_dict(verdict: GuardVerdict) -> dict[str, object]:
    """JSON-friendly summary (node diagnostics, evaluation extras)."""
    return {
        'decision': verdict.decision,
        'reason': verdict.reason,
        'confidence': verdict.confidence,
        **{k: v for k, v in asdict(verdict).items() if k == 'evidence'},
    }
