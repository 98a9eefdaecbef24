"""One keyframe through the fusion: stage-2 selection, alignment, interpolation, fallbacks.

``fuse_keyframe`` is what the ROS ``fusion_node`` and the ``fused*`` evaluation methods
call. Numpy in, numpy out; the interpolation runs on torch (``FusionConfig.device``).

Steps (paper §III-C/§III-D):

1. stage-1 points = the given mask where ``m`` and ``s`` are finite (``n_stage1``); for a
   metric source whose points lie on its depth edges only, their corrections cut to what the
   edges do not explain (``edge_points.py``, ``edge_ratio``); less the points of a
   silhouette's halo when the keyframe image is given (``occlusion.py``; a relative or
   inverse source after step 3 instead, once it is a depth);
2. RANSAC ``m ≈ a·s + b`` over them; inliers = Ω (``n_omega``), or a given Ω (oracle);
3. ``s ← a·s + b`` when aligning (default: only for non-metric sources), in the model's own
   space (``alignment.py``); pixels mapped to a non-positive depth are NaN (``n_nonpositive``);
4. ``f = s + Σ W (m - s)`` over Ω, exact or fast; confidence from the support distance.

Fallbacks never raise: the single-view depth is returned (its non-finite and non-positive
values set to NaN by ``valid_depth.sanitize_depth``, like every output; not aligned: without a
fit there is nothing to align with), confidence 0, and ``fallback`` names the reason —
``no_single_view`` (``s`` has no finite pixel; depth all NaN), ``too_few_points`` (fewer
stage-1 points than ``max(2, ransac_min_inliers)``, or fewer than 2 given Ω points when the
source needs aligning), ``no_consensus`` (no line with ``ransac_min_inliers`` inliers),
``empty_omega`` (a given Ω without a usable point).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .. import vml_warmup  # noqa: F401  (MKL VML dispatch resolved before the first parallel sqrt / exp)
from .agreement import agreement
from .alignment import AlignedDepth, apply_alignment, fit_alignment
from .consistency import ConsistencyConfig, consistent_points, stage3_candidates
from .edge_points import check_edge_ratio, edge_explained
from .guard import DECISION_CONFIDENCE, GuardConfig, GuardVerdict, MultiViewEvidence, assess
from .guard_apply import guarded_depth, limit_reach
from .interpolation import (
    DEFAULT_CHUNK_ELEMENTS,
    MAX_CERTAINTY_FLOOR,
    MODES,
    check_certainty_floor,
    confidence_from_support,
    interpolate,
)
from .occlusion import check_min_step, halo_points
from .precision import check_half_weight, precision_weights
from .selection import MIN_DEPTH, OUTPUT_KINDS, LinearFit, check_output_kind
from .shared_scale import points_factor, scale_weight, weighed_points
from .stream_scale import StreamScale
from .subsample import seeded_subsample
from .valid_depth import sanitize_depth
from .weights import WeightParams, check_structure_scale, check_weight_params

log = logging.getLogger(__name__)

RANSAC_MODELS = ('affine', 'scale')
#: With ``max_points`` set, the guard checks a seeded sample of this many times ``max_points``
#: points of Ω (its local test costs ~70 ms of CPU at the filter's 27k points, ~20 ms at
#: 8192), enough that the capped Ω can still be ``max_points`` trusted points.
GUARD_SAMPLE_FACTOR = 2
FALLBACKS = ('no_single_view', 'too_few_points', 'no_consensus', 'empty_omega')

#: One line per ``FusionConfig`` field, for ROS parameter descriptions and docs.
FUSION_PARAMETER_DESCRIPTIONS: dict[str, str] = {
    'sigma1': 'proximity scale of W1 (pixels of the working grid)',
    'sigma2': 'floor of the gradient differences in W2 (metres per pixel); bounds W2 by 1/sigma2^2',
    'sigma3': 'floor added to W3 and W4 so no point of omega gets a vanishing weight',
    'weights': "weight factors: 'w1' (proximity), 'w1w2' (+ gradients), 'all' (+ planes, the paper)",
    'structure_scale': 'length (m) in which W2-W4 compare depths and depth gradients; 1 = the paper',
    'mode': "'exact': every pixel against every point; 'fast': exact on a coarse grid, guided upsampling",
    'fast_stride': 'fast mode: exact offsets every fast_stride pixels in x and y',
    'fast_refine': 'fast mode: pixels whose structure matches no coarse neighbour this well (0..1) are exact',
    'chunk_elements': 'pixel-point pairs per chunk of the exact sum (8 bytes each at most, bounds memory)',
    'compile_kernel': 'fuse the weight kernel with torch.compile (first call compiles; eager if it fails)',
    'ransac_threshold': 'stage 2: inlier residual |m - (a s + b)| in metres (fraction of depth if relative)',
    'ransac_relative': 'stage 2: ransac_threshold is a fraction of the predicted depth instead of metres',
    'ransac_iterations': 'stage 2: random two-point hypotheses',
    'ransac_model': "stage 2 model: 'affine' m = a s + b, 'scale' m = a s; auto: scale for metric sources",
    'metric_scale_range': 'stage 2, metric sources: only fits with 1/r <= a <= r are plausible (r = this)',
    'ransac_min_inliers': 'stage 2: fewer inliers than this is no consensus (single-view depth published)',
    'seed': 'seed of the RANSAC sampling and of the max_points subsampling (deterministic output)',
    'align_scale': "map s <- a s + b before fusing; 'auto': only for non-metric single-view sources",
    'max_points': (
        'fuse at most this many points of omega (a seeded uniform subsample: the cost is '
        'pixels x |omega|); -1 or auto: all of them'
    ),
    'std_half_weight': (
        "each point's weight times h^2 / (h^2 + r^2), r its multi-view relative depth std, "
        'h this (a point with r = h counts half; 0: off, the paper)'
    ),
    'agreement_tau': (
        'confidence times exp(-spread / (tau x depth)), spread the std of the offsets of the points '
        'within agreement_sigma px (a pixel whose points disagree by tau of its depth: x0.37; 0: off)'
    ),
    'agreement_sigma': 'window (Gaussian sigma, working-grid pixels) of the points agreement_tau reads',
    'certainty_floor': (
        'every correction times M / (M + k), M the total weight of the points at the pixel, k this '
        "times one point's largest weight (as if from all of omega, not the max_points subsample); "
        'fades corrections where no point resembles the pixel (0: off, the paper)'
    ),
    'certainty_gain': (
        'raises k per keyframe to this x (mv_noise / e)^2 when that is larger, e the single-view error '
        "at the points (the guard's single_error and global scale): a single-view depth nearly as "
        'precise as the points keeps more of itself (0: off)'
    ),
    'halo_min_step': (
        "drop the points in a silhouette's halo (the foreground's depth on background pixels next to "
        "it, a patch matcher's fattening): on the far side of an image edge where the single-view log "
        'depth steps by more than this beyond a ramp, with a depth nearer than halfway; needs the '
        'keyframe image (0: off)'
    ),
    'edge_ratio': (
        "metric sources: where a keyframe's points lie on the single view's depth edges at least "
        'this many times as often as its pixels (and at least 45 % of them), a point the single '
        'view reaches within 5 px counts as agreeing with it, and only the rest of its correction '
        'is fused (0: off)'
    ),
    'guard': 'degrade the fusion per keyframe when the multi-view evidence cannot be trusted (guard.*)',
}


@dataclass
class FusionConfig:
    """Parameters of :func:`fuse_keyframe` (also the ``fusion.*`` ROS parameters).

    Paper values: σ1 = 15 px, σ2 = 0.1, σ3 = 1e-3, all four weights, depths in metres
    (``structure_scale`` 1; the default 0.3 sharpens W2-W4, docs/fusion.md).
    """

    sigma1: float = 15.0
    sigma2: float = 0.1
    sigma3: float = 1e-3
    weights: str = 'all'
    #: Length (m) in which W2-W4 measure depths and depth gradients (1: the paper's metres;
    #: 0.3: a point 30 cm off a pixel's plane weighs 1/e, docs/fusion.md "Structure scale").
    structure_scale: float = 0.3
    mode: str = 'exact'
    fast_stride: int = 4
    fast_refine: float = 0.3
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS
    compile_kernel: bool = False
    ransac_threshold: float = 0.35
    ransac_relative: bool = True
    ransac_iterations: int = 200
    ransac_model: str | None = None
    metric_scale_range: float = 2.0
    ransac_min_inliers: int = 10
    seed: int = 0
    align_scale: bool | None = None
    max_points: int | None = None
    #: Precision weight of each point from its multi-view std (``precision.py``; 0: off).
    std_half_weight: float = 0.0
    #: The confidence's agreement factor (``agreement.py``): relative spread of the nearby
    #: points' offsets that divides it by e (0: off, the support confidence alone), and its window.
    agreement_tau: float = 0.05
    agreement_sigma: float = 8.0
    #: Certainty floor κ of the interpolation (``interpolation.certainty_share``), as a
    #: fraction of one point's largest weight, for the whole Ω (0: off, the paper).
    certainty_floor: float = 0.1
    #: κ also follows the single-view depth's precision against the points' (guard evidence):
    #: at least this × (mv_noise / e)², e its error at the points (0: off, the fixed floor alone).
    certainty_gain: float = 30.0
    #: Points in a silhouette's halo leave Ω (``occlusion.py``) where the single-view depth
    #: steps by more than this (log depth) at the edge; 0: off, every stage-2 point stays.
    halo_min_step: float = 0.1
    #: Points concentrated on the single view's depth edges (``edge_points.py``): this many times
    #: the pixels' rate, and their corrections within the edge's range are no evidence; 0: off.
    edge_ratio: float = 2.8
    #: Check the evidence per keyframe and degrade gracefully (``guard.py``, ``GuardConfig``).
    guard: bool = True
    device: str = 'cpu'

    def __post_init__(self) -> None:
        check_weight_params(self.sigma1, self.sigma2, self.sigma3, self.weights)
        check_structure_scale(self.structure_scale)
        if self.mode not in MODES:
            raise ValueError(f'mode must be one of {", ".join(MODES)}, got {self.mode!r}')
        for name in ('fast_stride', 'chunk_elements', 'ransac_iterations'):
            if int(getattr(self, name)) < 1:
                raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')
        if self.ransac_min_inliers < 2:
            raise ValueError(f'ransac_min_inliers must be >= 2, got {self.ransac_min_inliers}')
        if not (np.isfinite(self.ransac_threshold) and self.ransac_threshold > 0):
            raise ValueError(f'ransac_threshold must be positive, got {self.ransac_threshold}')
        if not (np.isfinite(self.agreement_tau) and self.agreement_tau >= 0):
            raise ValueError(f'agreement_tau must be >= 0 (0: off), got {self.agreement_tau}')
        if not (np.isfinite(self.agreement_sigma) and self.agreement_sigma > 0):
            raise ValueError(
                f'agreement_sigma must be a positive number of pixels, got {self.agreement_sigma}'
            )
        if not 0.0 <= self.fast_refine <= 1.0:
            raise ValueError(f'fast_refine must be in [0, 1], got {self.fast_refine}')
        if self.ransac_model not in (None, *RANSAC_MODELS):
            raise ValueError(
                f'ransac_model must be one of {", ".join(RANSAC_MODELS)} or None, got {self.ransac_model!r}'
            )
        if not (np.isfinite(self.metric_scale_range) and self.metric_scale_range >= 1.0):
            raise ValueError(
                f'metric_scale_range must be a finite number >= 1, got {self.metric_scale_range}'
            )
        check_half_weight(self.std_half_weight)
        check_certainty_floor(self.certainty_floor)
        check_min_step(self.halo_min_step)
        check_edge_ratio(self.edge_ratio)
        if not (np.isfinite(self.certainty_gain) and self.certainty_gain >= 0):
            raise ValueError(
                f'certainty_gain must be a finite number >= 0 (0: off), got {self.certainty_gain}'
            )
        if self.max_points is not None and self.max_points < 1:
            raise ValueError(f'max_points must be >= 1 or None, got {self.max_points}')

    @property
    def weight_params(self) -> WeightParams:
        return WeightParams(self.sigma1, self.sigma2, self.sigma3, self.weights, self.structure_scale)

    def model(self, output_kind: str) -> str:
        """Stage-2 model: as configured, else ``scale`` for metric sources (``affine`` otherwise)."""
        if self.ransac_model is not None:
            return self.ransac_model
        return 'scale' if output_kind == 'metric_depth' else 'affine'

    def scale_range(self, output_kind: str) -> tuple[float, float]:
        """Plausible ``a`` of the stage-2 fit: within ``metric_scale_range`` of 1 for a metric
        source, any positive value otherwise."""
        if output_kind != 'metric_depth':
            return (0.0, np.inf)
        return (1.0 / self.metric_scale_range, self.metric_scale_range)

    def aligns(self, output_kind: str) -> bool:
        """Whether ``s`` is mapped by the fit: as configured, else for non-metric sources."""
        return output_kind != 'metric_depth' if self.align_scale is None else bool(self.align_scale)


@dataclass
class FusionResult:
    """Fused keyframe. ``depth``/``confidence`` float32 HxW (NaN depth where ``s`` is NaN);
    ``omega_mask`` the points fused; ``a, b`` the stage-2 line (1, 0 without one);
    ``fallback`` None or one of :data:`FALLBACKS`."""

    depth: np.ndarray
    confidence: np.ndarray
    omega_mask: np.ndarray
    a: float
    b: float
    n_stage1: int
    n_omega: int
    fallback: str | None = None
    #: The single-view depth the interpolation started from (aligned when aligning).
    single_aligned: np.ndarray | None = None
    #: Pixels whose aligned depth (or inverse depth) was not positive: NaN in ``depth``.
    n_nonpositive: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    #: The guard's step on the ladder (``guard.DECISIONS``), why, and the keyframe confidence
    #: that scaled ``confidence``; ``full`` / 1.0 when the guard is off.
    decision: str = 'full'
    decision_reason: str = ''
    keyframe_confidence: float = 1.0
    #: The evidence the guard measured (``guard.GuardVerdict.evidence``) and, whenever the
    #: keyframe was interpolated, ``certainty`` (the share of the correction the floor kept)
    #: and ``certainty_floor`` (the κ it used, :func:`keyframe_floor`).
    evidence: dict[str, float] = field(default_factory=dict)
    #: True when the keyframe has no depth at all (every pixel NaN) because the single-view
    #: source needs an alignment (relative or inverse depth, or ``align_scale``) and none was
    #: trusted: see :func:`withheld`.
    withheld: bool = False
    #: True on the keyframe where ``stream_scale`` first found the points in another unit than
    #: the single view (the caller says it once: ``StreamScale.describe``).
    stream_scale_found: bool = False


def fuse_keyframe(
    single_depth: np.ndarray,
    mv_depth: np.ndarray,
    stage1_mask: np.ndarray | None,
    config: FusionConfig | None = None,
    output_kind: str = 'metric_depth',
    *,
    stream_scale: StreamScale | None = None,
    stamp: int | None = None,
    **options: Any,
) -> FusionResult:
    """Fuse one keyframe (all inputs HxW on the working grid): :func:`_fuse`, whose keyword
    ``options`` (``omega_mask``, ``guard_config``, ``evidence``, ``consistency_config``,
    ``image``) it passes on.

    ``stream_scale``: the stream's scale (``stream_scale.py``) a metric single view is
    multiplied by first, observed on this keyframe (``stamp``: its stamp, or any increasing
    key); ``evidence['stream_scale']`` then holds the factor used, and ``scale_jump`` this
    keyframe's log factor against the stream's where it was judged. A keyframe off the stream
    by more than ``stream_scale.max_jump`` keeps its single view (:func:`_off_the_stream`).
    """
    found, factor, jump, jump_reason = False, 1.0, None, None
    if stream_scale is not None and output_kind == 'metric_depth':
        single_depth, factor, found = stream_scale.scaled(single_depth, mv_depth, stage1_mask, stamp)
        # read here: a source this call does not observe must not show the last keyframe's jump
        jump, jump_reason = stream_scale.jump, stream_scale.jump_reason()
    result = _fuse(
        single_depth, mv_depth, stage1_mask, config, output_kind, scale_jump_reason=jump_reason, **options
    )
    if stream_scale is not None:
        result.evidence['stream_scale'] = factor
        if jump is not None:
            result.evidence['scale_jump'] = jump
        result.stream_scale_found = found
    return result


def _fuse(
    single_depth: np.ndarray,
    mv_depth: np.ndarray,
    stage1_mask: np.ndarray | None,
    config: FusionConfig | None = None,
    output_kind: str = 'metric_depth',
    *,
    omega_mask: np.ndarray | None = None,
    guard_config: GuardConfig | None = None,
    evidence: MultiViewEvidence | None = None,
    consistency_config: ConsistencyConfig | None = None,
    image: np.ndarray | None = None,
    scale_jump_reason: str | None = None,
) -> FusionResult:
    """Fuse one keyframe (all inputs HxW on the working grid).

    ``single_depth``: the single-view map (``output_kind`` units); ``mv_depth``: semi-dense
    multi-view depth (m, NaN = none); ``stage1_mask``: stage-1 selected pixels (None = every
    multi-view estimate). ``omega_mask`` replaces stage 2 by a given Ω (the oracle
    selection); the alignment is then a least-squares fit on it, and the guard is skipped
    (a given Ω is trusted). ``guard_config`` / ``evidence``: the guard's thresholds and the
    optional per-pixel multi-view evidence (``guard.MultiViewEvidence``).
    ``consistency_config``: stage 3 (``consistency.py``; off by default): every multi-view
    estimate of the stage-2 band tested against its neighbours, skipped with a given Ω.
    ``image``: the keyframe (grey or RGB) for the halo test (``occlusion.py``,
    ``halo_min_step``); without it the test is skipped (``evidence['halo_checked']`` 0).
    ``scale_jump_reason``: why this keyframe's points are off the stream's scale
    (``StreamScale.jump_reason``), or None: with the guard on, the keyframe keeps its single view.
    """
    config = config or FusionConfig()
    check_output_kind(output_kind)
    needs_fit = _needs_fit(config, output_kind)
    s = _image(single_depth, 'single-view depth')
    m = _image(mv_depth, 'multi-view depth')
    if m.shape != s.shape:
        raise ValueError(f'multi-view depth {m.shape} and single-view depth {s.shape} differ in size')
    stage1 = _mask(stage1_mask, s.shape, 'stage1_mask') if stage1_mask is not None else np.isfinite(m)
    with np.errstate(invalid='ignore'):
        usable = np.isfinite(s) & np.isfinite(m) & (m > 0)
    stage1 = stage1 & usable
    n_stage1 = int(stage1.sum())
    t0 = time.perf_counter()

    if not np.isfinite(s).any():
        return _fallback(s, stage1, n_stage1, 'no_single_view', needs_fit)
    halo: dict[str, float] = {}
    if omega_mask is not None:
        omega = _mask(omega_mask, s.shape, 'omega_mask') & usable
        if not omega.any():
            return _fallback(s, stage1, n_stage1, 'empty_omega', needs_fit)
        fit = fit_alignment(s[omega], m[omega], output_kind, config, robust=False)
        if not fit.ok and config.aligns(output_kind):
            return _fallback(s, stage1, n_stage1, 'too_few_points', needs_fit)
    else:
        if output_kind == 'metric_depth':
            # Points only on the single view's edges first: those its edges explain agree with it
            # (a halo among them), and neither the line nor the guard should read them as errors.
            m, edges = edge_explained(s, m, stage1, config.edge_ratio)
            # A metric source is a depth already: its halo leaves before stage 2, whose line
            # is then fitted without it (the halo is too near by the whole step, a bias).
            stage1, halo = _without_halo(image, s, m, stage1, config.halo_min_step, config.device)
            halo.update(edges)
        fit = fit_alignment(s[stage1], m[stage1], output_kind, config)
        if not fit.ok:
            log.debug('stage 2 failed (%s) on %d stage-1 points', fit.reason, n_stage1)
            return _fallback(s, stage1, n_stage1, fit.reason or 'no_consensus', needs_fit)
        omega = np.zeros(s.shape, dtype=bool)
        omega[stage1] = fit.inliers
    t_select = time.perf_counter() - t0

    aligned = apply_alignment(s, fit) if config.aligns(output_kind) else AlignedDepth(s, 0)
    base = aligned.depth
    consistency_config = consistency_config or ConsistencyConfig()
    if omega_mask is None and output_kind != 'metric_depth':
        # Relative and inverse sources are a depth only once aligned.
        omega, halo = _without_halo(image, base, m, omega, config.halo_min_step, config.device)
    stage3: dict[str, float] = {}
    if consistency_config.enabled and omega_mask is None:
        candidates = stage3_candidates(
            consistency_config.candidates,
            omega,
            usable,
            s,
            m,
            fit,
            config.ransac_threshold,
            config.ransac_relative,
        )
        omega, stage3 = consistent_points(base, m, omega, candidates, consistency_config, config.device)
    guard_config = guard_config or GuardConfig()
    verdict = None
    if config.guard and omega_mask is None:
        sample = None if config.max_points is None else GUARD_SAMPLE_FACTOR * config.max_points
        # The halo's points leave stage 1 as well: the inlier ratio asks whether the fit explains
        # the points the multi-view stage offered, and those were dropped for another reason.
        offered = n_stage1 - int(halo.get('n_halo', 0))
        verdict = assess(
            base,
            m,
            omega,
            offered,
            guard_config,
            evidence,
            sample=sample,
            seed=config.seed,
            device=config.device,
        )
        verdict.evidence.update(halo)
        verdict.evidence.update(stage3)
        if guard_config.shared_scale and needs_fit is None:
            m = _weigh_shared_scale(m, verdict)
        if scale_jump_reason is not None:
            verdict = _off_the_stream(verdict, scale_jump_reason)
        if verdict.decision not in ('full', 'fewer_points'):
            return _guarded(aligned, m, fit, n_stage1, verdict, config, guard_config, needs_fit)
        omega = verdict.trusted
    omega = omega & np.isfinite(base)
    uncapped = int(np.count_nonzero(omega))
    omega = _cap_points(omega, config.max_points, config.seed)
    # A subsample of Ω has that share of its weight: the floor follows, so the fade is the
    # whole Ω's whatever max_points (or the load) keeps.
    kappa = keyframe_floor(config, verdict)
    floor = kappa * np.count_nonzero(omega) / max(uncapped, 1)
    t1 = time.perf_counter()
    interp = interpolate(
        base,
        m,
        omega,
        config.weight_params,
        mode=config.mode,
        fast_stride=config.fast_stride,
        fast_refine=config.fast_refine,
        chunk_elements=config.chunk_elements,
        device=config.device,
        compile_kernel=config.compile_kernel,
        point_weight=precision_weights(evidence.relative_std if evidence else None, config.std_half_weight),
        certainty_floor=floor,
    )
    with np.errstate(invalid='ignore'):
        depth = np.maximum(base + interp.offset, MIN_DEPTH).astype(np.float32)
    depth[~np.isfinite(base)] = np.nan
    if verdict is not None and guard_config.reach > 0:
        radius = guard_config.reach * base.shape[1]
        depth, coverage = limit_reach(depth, base, interp.support_distance, radius)
        verdict.evidence['coverage'] = coverage
    depth, _ = sanitize_depth(depth)
    confidence = confidence_from_support(interp.support_distance, config.sigma1)
    confidence *= agreement(
        depth, base, m, omega, config.agreement_sigma, config.agreement_tau, config.device
    )
    confidence[~np.isfinite(depth)] = 0.0
    if verdict is not None:
        confidence *= np.float32(verdict.confidence)
    result = FusionResult(
        depth=depth,
        confidence=confidence,
        omega_mask=omega,
        a=fit.a,
        b=fit.b,
        n_stage1=n_stage1,
        n_omega=int(omega.sum()),
        single_aligned=base,
        n_nonpositive=aligned.n_nonpositive,
        timings={'selection_s': t_select, 'interpolation_s': time.perf_counter() - t1},
        **_verdict_fields(verdict),
    )
    # With the guard or without: how much of the correction the certainty floor kept.
    result.evidence.update(halo)
    result.evidence['certainty'] = interp.kept
    result.evidence['certainty_floor'] = kappa
    return result


def _without_halo(
    image: np.ndarray | None,
    base: np.ndarray,
    m: np.ndarray,
    omega: np.ndarray,
    min_step: float,
    device: str = 'cpu',
) -> tuple[np.ndarray, dict[str, float]]:
    """Ω less the points in a silhouette's halo (``occlusion.halo_points``), and the evidence:
    ``halo_checked`` (0 when the test is off or the keyframe image is missing) and ``n_halo``."""
    if min_step <= 0 or image is None:
        return omega, {'halo_checked': 0.0, 'n_halo': 0.0}
    halo = halo_points(image, base, m, omega, min_step, device)
    return omega & ~halo, {'halo_checked': 1.0, 'n_halo': float(np.count_nonzero(halo))}


def keyframe_floor(config: FusionConfig, verdict: GuardVerdict | None) -> float:
    """κ of this keyframe, in units of one point's largest weight: ``certainty_floor``, raised
    to ``certainty_gain × (mv_noise / e)²`` when the guard measured both, ``e`` the single-view
    error at the points (``single_error`` and the log of the global scale, in quadrature).

    Normalised convolution with a certainty floor weighs "no correction" against the points;
    the floor's right size is the single-view depth's precision relative to a point's. A
    network whose error at the points is a few times the points' noise (adapted to this
    scene, or a good metric model) earns a floor of its own: corrections then stay where many
    points agree, and do not spread the points' residual error over the pixels between them
    (docs/fusion.md "Certainty floor"). Capped at ``MAX_CERTAINTY_FLOOR``.
    """
    kappa = config.certainty_floor
    if config.certainty_gain <= 0 or verdict is None:
        return kappa
    noise = verdict.evidence.get('mv_noise', np.nan)
    # The single-view error at the points: its spread about the fit (``single_error``) and
    # the global scale the points give it (a network off by one factor everywhere, as the
    # shipped one is on TUM fr1_xyz, is precise about the fit and still far off).
    error = float(np.hypot(verdict.evidence.get('single_error', np.nan), np.log(verdict.scale)))
    if not (np.isfinite(noise) and np.isfinite(error)):
        return kappa
    ratio = noise / error if error > 0 else np.inf
    return float(min(max(kappa, config.certainty_gain * ratio * ratio), MAX_CERTAINTY_FLOOR))


def _weigh_shared_scale(m: np.ndarray, verdict: GuardVerdict) -> np.ndarray:
    """The points moved towards the single view's scale by what their shared std leaves of
    theirs (``shared_scale.py``); the verdict's scale becomes the one taken, and the evidence
    gets ``scale_weight`` (the share) where the guard read a shared std."""
    shared = verdict.evidence.get('shared_std')
    if shared is None:
        return m
    weight = scale_weight(verdict.evidence.get('single_error', np.nan), shared, verdict.scale)
    verdict.evidence['scale_weight'] = weight
    factor = points_factor(verdict.scale, weight)
    verdict.scale *= factor  # scale^weight: the share of the points' scale taken
    return weighed_points(m, factor)


def _off_the_stream(verdict: GuardVerdict, reason: str) -> GuardVerdict:
    """``single_view`` for a keyframe whose points sit off the stream's scale.

    Why not a smaller step down the ladder: every lower step but the last takes the points'
    scale, and that scale is what is off. Points consistent among themselves and 2x off the
    stream's single-view ratio are a shared error (matches a wave along the line under the
    poses' noise, kept by frames at equal baselines) far more often than a metric network's
    scale jumping 2x between keyframes of one stream (``stream_scale.py``)."""
    if verdict.decision == 'single_view':
        return verdict
    return dataclasses.replace(
        verdict,
        decision='single_view',
        reason=reason,
        trusted=np.zeros_like(verdict.trusted),
        confidence=DECISION_CONFIDENCE['single_view'],
    )


def _verdict_fields(verdict: GuardVerdict | None) -> dict:
    if verdict is None:
        return {}
    return {
        'decision': verdict.decision,
        'decision_reason': verdict.reason,
        'keyframe_confidence': verdict.confidence,
        'evidence': dict(verdict.evidence),
    }


def _guarded(
    aligned: AlignedDepth,
    m: np.ndarray,
    fit: LinearFit,
    n_stage1: int,
    verdict: GuardVerdict,
    config: FusionConfig,
    guard_config: GuardConfig,
    needs_fit: str | None,
) -> FusionResult:
    """A keyframe the guard stepped down to ``scale_only``, ``single_scaled`` or ``single_view``.

    It starts from ``aligned.depth``: ``s`` itself, or ``s`` mapped by the fit when aligning (a
    non-metric source must be in metres whatever the decision). ``single_view`` of a source
    that needs the fit (``needs_fit``: its output kind) is withheld (:func:`withheld`): the
    guard has just said the fit's points cannot be trusted, so nothing is in metres."""
    base = aligned.depth
    depth, confidence = guarded_depth(base, m, verdict, config, guard_config)
    depth, _ = sanitize_depth(depth)
    confidence[~np.isfinite(depth)] = 0.0
    withhold = verdict.decision == 'single_view' and needs_fit is not None
    if withhold:
        depth, confidence, reason = withheld(depth.shape, verdict.reason, needs_fit)
        verdict = dataclasses.replace(verdict, reason=reason)
    return FusionResult(
        depth=depth,
        confidence=confidence,
        omega_mask=verdict.trusted,
        a=fit.a,
        b=fit.b,
        n_stage1=n_stage1,
        n_omega=int(verdict.trusted.sum()),
        single_aligned=base,
        n_nonpositive=aligned.n_nonpositive,
        withheld=withhold,
        **_verdict_fields(verdict),
    )


def withheld(shape: tuple[int, ...], reason: str, output_kind: str) -> tuple[np.ndarray, np.ndarray, str]:
    """No depth (NaN), confidence 0 and the reason, for a keyframe whose source needs an
    alignment that this keyframe does not have.

    Why not the single-view map as it is: a relative or inverse-depth output is in no unit
    (and with ``align_scale`` the poses are not in metres), so passing it on, or mapping it by
    a fit the guard rejected, publishes numbers that look like depth and are not (7-Scenes,
    ``simulated_relative``: 2.3 and 4.2 m MAE on the three keyframes concerned, against
    0.24 m for the rest). A consumer gets NaN, the decision ``single_view`` and this reason.
    """
    nan = np.full(shape, np.nan, dtype=np.float32)
    note = f'{reason}; depth withheld: the {output_kind} source needs an alignment and has no trusted one'
    return nan, np.zeros(shape, dtype=np.float32), note


def _needs_fit(config: FusionConfig, output_kind: str) -> str | None:
    """``output_kind`` when the source is only usable through the fit, else None."""
    return output_kind if config.aligns(output_kind) else None


def _fallback(
    s: np.ndarray, stage1: np.ndarray, n_stage1: int, reason: str, needs_fit: str | None
) -> FusionResult:
    """The single-view depth unchanged, confidence 0, flagged with ``reason``; withheld
    (:func:`withheld`) when the source needs the alignment that just failed (``needs_fit``:
    its output kind)."""
    log.debug('fusion fallback: %s', reason)
    depth, invalid = sanitize_depth(s)  # a fallback passes s on: never its inf / negative codes
    if invalid:
        log.debug('fusion fallback %s: %d non-finite or non-positive depths set to NaN', reason, invalid)
    note = reason
    if needs_fit:
        depth, _, note = withheld(s.shape, reason, needs_fit)
    return FusionResult(
        depth=depth,
        confidence=np.zeros(s.shape, dtype=np.float32),
        omega_mask=np.zeros(s.shape, dtype=bool),
        a=1.0,
        b=0.0,
        n_stage1=n_stage1,
        n_omega=0,
        fallback=reason,
        single_aligned=s,
        decision='single_view',
        decision_reason=note,
        keyframe_confidence=0.0,
        withheld=needs_fit is not None,
    )


def _cap_points(omega: np.ndarray, max_points: int | None, seed: int) -> np.ndarray:
    """At most ``max_points`` points of Ω, a seeded uniform subsample (bounds the cost)."""
    count = int(omega.sum())
    if max_points is None or count <= max_points:
        return omega
    keep = np.flatnonzero(omega)[seeded_subsample(count, max_points, seed)]
    capped = np.zeros_like(omega)
    capped.ravel()[keep] = True
    log.debug('omega capped from %d to %d points', count, max_points)
    return capped


def _image(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or min(a.shape) < 2:
        raise ValueError(f'{what} must be an HxW image (H, W >= 2), got shape {a.shape}')
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f'{what} must be floating point (metres, NaN = none), got {a.dtype}')
    return a.astype(np.float32, copy=False)


def _mask(a: np.ndarray, shape: tuple[int, ...], what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.shape != shape:
        raise ValueError(f'{what} {a.shape} must have the size of the depth images {shape}')
    return a.astype(bool, copy=False)


__all__ = [
    'FALLBACKS',
    'FUSION_PARAMETER_DESCRIPTIONS',
    'OUTPUT_KINDS',
    'FusionConfig',
    'FusionResult',
    'LinearFit',
    'fuse_keyframe',
]


def warm_up(config: FusionConfig, width: int = 320, height: int = 240) -> float:
    """Run the fusion once on a synthetic planes-and-boxes keyframe; returns the seconds it took.

    With ``compile_kernel`` the first call compiles the kernels (about 10 s on 2 CPU cores,
    also with torch's on-disk cache): a node does it at start-up so its first keyframe is not
    late. Kernels are compiled for dynamic shapes, so other grid sizes and |Ω| reuse them.
    """
    from .scenes import make_scene

    scene = make_scene(width, height, n_points=max(8, width * height // 100), seed=0)
    start = time.perf_counter()
    fuse_keyframe(scene.single, scene.multi, None, config)
    return time.perf_counter() - start
