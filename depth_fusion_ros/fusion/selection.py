"""Stage 2 of the multi-view point selection (paper §III-D): a RANSAC line ``m ≈ a·s + b``.

Stage 1 (the best fraction by photometric × geometric score, in
:mod:`depth_fusion_ros.multiview.semidense`) still lets through multi-view points with large
errors. The single-view depth ``s`` is wrong by smooth, segment-wise deformations but not by
the isolated, uncorrelated jumps of a wrong match, so a *single* linear model between the
stage-1 multi-view depths and ``s`` at the same pixels, fitted over the whole image, finds
the spurious points as its outliers (the paper notes that small patches find consensus with
the outliers). Its inliers are Ω. The same fit maps a non-metric ``s`` into metres.

Single-view sources announce an *output kind*:

* ``metric_depth`` — metres; the model is ``m ≈ a·s + b``;
* ``relative_depth`` — depth up to an affine map; same model, and ``s`` must be mapped;
* ``inverse_depth`` — inverse depth (or disparity) up to an affine map; the model is
  ``1/m ≈ a·s + b`` and the mapped depth ``1/(a·s + b)``.

Residuals are always measured in metres of depth, so the threshold means the same for every
kind. Hypotheses come from seeded random pairs (deterministic for a seed), are scored with
the truncated quadratic loss (MSAC; on a seeded subsample of ``SCORE_POINTS`` points when
there are more) and the best one is refined by least squares on its inliers (all points)
until the inlier set stops changing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

OUTPUT_KINDS = ('metric_depth', 'relative_depth', 'inverse_depth')

#: Smallest depth a mapped single-view value may take (m); keeps 1/(a·s+b) finite.
MIN_DEPTH = 1e-2
#: Hypotheses x points evaluated at once (float64, 512 KiB): a block that stays in the
#: cache scores 200 hypotheses x 4096 points in about a third of the time of one 6.5 MB pass.
RESIDUAL_BLOCK = 1 << 16
#: Least-squares refinements of the best hypothesis at most.
REFINEMENTS = 5
#: Hypotheses are scored on at most this many points (a seeded subsample beyond; the inliers
#: and the refinement always use every point). The temporal filter sends 20-40k points per
#: keyframe: scoring 200 hypotheses on all of them took 40-200 ms of the fusion node's
#: keyframe, while the MSAC cost of 4096 random points ranks the hypotheses as well (its
#: relative standard error is below 2 %); the refinement then settles on the same line.
SCORE_POINTS = 4096


def check_output_kind(output_kind: str) -> None:
    if output_kind not in OUTPUT_KINDS:
        raise ValueError(f'output_kind must be one of {", ".join(OUTPUT_KINDS)}, got {output_kind!r}')


@dataclass
class LinearFit:
    """Result of stage 2.

    ``inliers`` is a bool mask over the points given to :func:`fit_ransac` (Ω). ``ok`` is
    False when no usable model exists; ``reason`` then says why (``too_few_points`` or
    ``no_consensus``) and ``a = 1, b = 0``.
    """

    a: float
    b: float
    inverse: bool
    inliers: np.ndarray
    ok: bool
    reason: str | None = None
    #: Largest inlier multi-view depth: bounds the mapped depth of ``inverse_depth`` sources.
    max_depth: float = np.inf

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    def predict(self, s: np.ndarray) -> np.ndarray:
        """Depth in metres predicted for single-view values ``s`` (float32, NaN kept).

        For inverse kinds ``a·s + b ≤ 0`` (beyond infinity) maps to ``10 x`` the farthest
        inlier; mapped depths are at least :data:`MIN_DEPTH`.
        """
        s = np.asarray(s, dtype=np.float64)
        lin = self.a * s + self.b
        if self.inverse:
            far = 10.0 * self.max_depth if np.isfinite(self.max_depth) else 1e3
            with np.errstate(divide='ignore', invalid='ignore'):
                depth = np.where(lin > 1.0 / far, 1.0 / lin, far)
            depth = np.where(np.isfinite(s), depth, np.nan)
        else:
            depth = lin
        with np.errstate(invalid='ignore'):
            return np.where(np.isnan(depth), np.nan, np.maximum(depth, MIN_DEPTH)).astype(np.float32)


def failed_fit(n: int, inverse: bool, reason: str) -> LinearFit:
    return LinearFit(1.0, 0.0, inverse, np.zeros(n, dtype=bool), ok=False, reason=reason)


def least_squares_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float] | None:
    """``y ≈ a·x + b`` by least squares; None when ``x`` has no spread."""
    if x.size < 2:
        return None
    xm, ym = float(x.mean()), float(y.mean())
    var = float(np.mean((x - xm) ** 2))
    if not var > 1e-12 * max(1.0, xm * xm):
        return None
    a = float(np.mean((x - xm) * (y - ym)) / var)
    return a, ym - a * xm


def _prediction(a: np.ndarray, b: np.ndarray, s: np.ndarray, inverse: bool) -> np.ndarray:
    """Predicted depth (m) of hypotheses ``(a, b)`` (shape (H,)) at points ``s`` (N,), (H, N):
    ``a·s + b``, or its inverse (``inf`` where not positive) for inverse-depth fits."""
    lin = np.multiply.outer(a, s)
    lin += b[:, None]
    if inverse:
        with np.errstate(divide='ignore'):
            return np.where(lin > 0, 1.0 / np.where(lin > 0, lin, 1.0), np.inf)
    return lin


def _residuals_thresholds(
    a: np.ndarray,
    b: np.ndarray,
    s: np.ndarray,
    m: np.ndarray,
    threshold: float,
    relative: bool,
    inverse: bool,
) -> tuple[np.ndarray, np.ndarray | float]:
    """``|m - prediction|`` (m) per hypothesis and point, (H, N), and the inlier thresholds:
    ``threshold`` metres, or that fraction of the predicted depth (H, N) when ``relative``.

    One prediction per call, the steps in place: this is the inner loop of RANSAC (200
    hypotheses x 4096 points per keyframe) and of its refinement (every point).
    """
    pred = _prediction(a, b, s, inverse)
    r = np.subtract(m[None, :], pred)
    np.abs(r, out=r)
    if not relative:
        return r, threshold
    np.abs(pred, out=pred)
    pred *= threshold
    return r, pred


def fit_ransac(
    s: np.ndarray,
    m: np.ndarray,
    *,
    threshold: float = 0.1,
    relative: bool = False,
    iterations: int = 200,
    min_inliers: int = 10,
    seed: int = 0,
    inverse: bool = False,
    affine: bool = True,
    scale_range: tuple[float, float] = (0.0, np.inf),
) -> LinearFit:
    """Robust ``m ≈ a·s + b`` (``1/m ≈ a·s + b`` when ``inverse``) over paired 1-D samples.

    ``threshold`` is the inlier residual in metres (a fraction of the predicted depth when
    ``relative``). Only increasing models (``a > 0``) are hypotheses: depth grows with
    single-view depth (and shrinks with inverse depth). Never raises on degenerate data:
    fewer than ``max(2, min_inliers)`` points give ``too_few_points``, no hypothesis with
    ``min_inliers`` inliers gives ``no_consensus``.
    """
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f'ransac_threshold must be positive, got {threshold}')
    if iterations < 1:
        raise ValueError(f'ransac_iterations must be >= 1, got {iterations}')
    if min_inliers < 2:
        raise ValueError(f'ransac_min_inliers must be >= 2 (a line needs two points), got {min_inliers}')
    s = np.asarray(s, dtype=np.float64).ravel()
    m = np.asarray(m, dtype=np.float64).ravel()
    if s.shape != m.shape:
        raise ValueError(f'single-view ({s.size}) and multi-view ({m.size}) samples differ in number')
    n = s.size
    usable = np.isfinite(s) & np.isfinite(m) & (m > 0)
    if int(usable.sum()) < max(2, min_inliers):
        return failed_fit(n, inverse, 'too_few_points')
    idx = np.flatnonzero(usable)
    su, mu = s[idx], m[idx]
    target = 1.0 / mu if inverse else mu

    rng = np.random.default_rng(seed)
    a, b = _hypotheses(su, target, iterations, rng, affine)
    plausible = (a >= scale_range[0]) & (a <= scale_range[1])
    a, b = a[plausible], b[plausible]
    if a.size == 0:
        return failed_fit(n, inverse, 'no_consensus')

    best_cost, best = np.inf, -1
    scored = np.arange(idx.size)
    if idx.size > SCORE_POINTS:  # its own stream: the hypotheses stay those of every point count
        scored = np.sort(np.random.default_rng([seed, 1]).choice(idx.size, SCORE_POINTS, replace=False))
    s_scored, m_scored = su[scored], mu[scored]
    block = max(1, RESIDUAL_BLOCK // scored.size)
    for start in range(0, a.size, block):
        sl = slice(start, start + block)
        cost, t = _residuals_thresholds(a[sl], b[sl], s_scored, m_scored, threshold, relative, inverse)
        with np.errstate(invalid='ignore'):
            cost /= t
        # fmin: a point predicted at infinity (an inverse fit's non-positive 1/depth: inf / inf)
        # is an outlier like any other, not a NaN that would poison the hypothesis' sum.
        np.fmin(cost, 1.0, out=cost)
        cost *= cost
        cost = cost.sum(axis=1)
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best = float(cost[k]), start + k
    a_best, b_best = float(a[best]), float(b[best])

    inl = _inliers(a_best, b_best, su, mu, threshold, relative, inverse)
    for _ in range(REFINEMENTS):
        refit = least_squares_line if affine else least_squares_scale
        line = refit(su[inl], target[inl])
        if line is None or not scale_range[0] <= line[0] <= scale_range[1]:
            break
        refined = _inliers(line[0], line[1], su, mu, threshold, relative, inverse)
        if refined.sum() < inl.sum():
            break
        a_best, b_best = line
        if np.array_equal(refined, inl):
            break
        inl = refined
    if int(inl.sum()) < min_inliers:
        return failed_fit(n, inverse, 'no_consensus')
    inliers = np.zeros(n, dtype=bool)
    inliers[idx[inl]] = True
    return LinearFit(a_best, b_best, inverse, inliers, ok=True, max_depth=float(mu[inl].max()))


def _hypotheses(
    s: np.ndarray, target: np.ndarray, iterations: int, rng: np.random.Generator, affine: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Increasing models through random minimal samples: two distinct points for a line,
    one point for a scale."""
    first = rng.integers(0, s.size, size=iterations)
    if affine:
        second = rng.integers(0, s.size - 1, size=iterations)
        second += second >= first  # two distinct points per hypothesis
        ds = s[second] - s[first]
        with np.errstate(divide='ignore', invalid='ignore'):
            a = (target[second] - target[first]) / ds
        b = target[first] - a * s[first]
    else:
        with np.errstate(divide='ignore', invalid='ignore'):
            a = target[first] / s[first]
        b = np.zeros_like(a)
    good = np.isfinite(a) & np.isfinite(b) & (a > 0)
    return a[good], b[good]


def least_squares_scale(x: np.ndarray, y: np.ndarray) -> tuple[float, float] | None:
    """``y ≈ a·x`` by least squares, as ``(a, 0)``; None without a usable point.

    ``einsum``, not ``np.dot``: the dot goes to OpenBLAS, whose worker threads (one per core
    unless OMP_NUM_THREADS says otherwise, as in a composed graph or ``evaluate``) now and then
    take milliseconds to wake when another process holds a core: a 13k-point fit then took
    14-16 ms on average against 8.6 ms with ``einsum``; on a quiet machine both take 7.3 ms,
    with the same scale to 1e-15.
    """
    xx = float(np.einsum('i,i->', x, x))
    return (float(np.einsum('i,i->', x, y)) / xx, 0.0) if x.size and xx > 0 else None


def inliers_of(fit: LinearFit, s: np.ndarray, m: np.ndarray, threshold: float, relative: bool) -> np.ndarray:
    """Which points ``(s, m)`` the line ``fit`` explains within the stage-2 inlier threshold:
    the test RANSAC itself applies, for points it was not fitted on."""
    return _inliers(fit.a, fit.b, s, m, threshold, relative, fit.inverse)


def _inliers(
    a: float, b: float, s: np.ndarray, m: np.ndarray, threshold: float, relative: bool, inverse: bool
) -> np.ndarray:
    r, t = _residuals_thresholds(np.array([a]), np.array([b]), s, m, threshold, relative, inverse)
    # A point the line puts at infinity (inverse fits) is an outlier, though inf <= inf.
    return (r[0] <= (t[0] if isinstance(t, np.ndarray) else t)) & np.isfinite(r[0])


def fit_least_squares(
    s: np.ndarray, m: np.ndarray, *, inverse: bool = False, affine: bool = True
) -> LinearFit:
    """Plain least-squares fit on points already known to be good (the oracle selection).

    Fails with ``too_few_points`` below two usable points (one for a scale) or without
    spread in ``s``.
    """
    s = np.asarray(s, dtype=np.float64).ravel()
    m = np.asarray(m, dtype=np.float64).ravel()
    usable = np.isfinite(s) & np.isfinite(m) & (m > 0)
    refit = least_squares_line if affine else least_squares_scale
    line = refit(s[usable], 1.0 / m[usable] if inverse else m[usable])
    if line is None:
        return failed_fit(s.size, inverse, 'too_few_points')
    return LinearFit(line[0], line[1], inverse, usable, ok=True, max_depth=float(m[usable].max()))
