"""Semi-dense multi-view depth by an inverse-depth sweep, with per-point quality scores (paper §III-A/D).

For every candidate pixel of the keyframe (image gradient above a threshold, or every pixel)
the photometric cost ``C(rho)`` (``cost_volume.sample_cost``: ``1 - ZNCC`` of a small patch,
averaged over the neighbours that see the point) is evaluated on ``num_samples`` inverse
depths spread uniformly in ``[1/max_depth, 1/min_depth]``; the best sample is refined on a
finer local grid and then sub-sample by a parabola. Inverse depth is the inverse z-depth
throughout (``depth = 1 / rho``).

Per estimated pixel it also returns what stage 1 of the point selection ranks by:

* **photometric score** = ``distinctiveness x sharpness``. Distinctiveness is the modified
  second-best ratio ``1 - c1 / c2`` (``c1`` the best cost, ``c2`` the lowest *other* local
  minimum of the coarse curve, more than ``second_min_exclusion`` samples away; the largest
  cost when there is none) - a monotone, bounded form of ``c2 / c1``, so that a near-zero best
  cost cannot make the score explode. Sharpness is the square root of the cost's curvature at
  the minimum per squared pixel of motion along the epipolar line: how sharp the "V" is, in
  image units so it does not depend on the sample spacing or the baseline (the square root
  makes it the inverse of the matching standard deviation in pixels, up to the noise level).
* **geometric score** = ``1 / sigma_rho = sqrt(sum_o J_o^2)`` (pixels per unit inverse depth),
  ``J_o = |dp_o/drho|`` the epipolar motion in neighbour ``o``: one pixel of matching error
  propagated into inverse-depth uncertainty. Low parallax (short baseline, pure rotation,
  points near the epipole) gives a low score. It is deliberately the *inverse-depth*
  uncertainty: the relative (``rho / sigma_rho``) or absolute (``rho^2 / sigma_rho``) depth
  precision also grows with the estimated ``rho`` itself, so they reward a wrong match for
  landing near the camera - and a uniform inverse-depth sweep puts most wrong matches there.
  On the synthetic room, ranking with ``rho / sigma_rho`` let 29 % gross errors (off by
  > 25 %) into the stage-1 points, ``1 / sigma_rho`` 5 %. ``depth_std`` holds the absolute
  ``sigma_z = sigma_rho / rho^2`` (m).

Memory is bounded: pixels are processed in chunks sized so the largest intermediate
(neighbours x channels x pixels x samples floats) stays below ``chunk_elements``, whatever
the number of samples.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from ..camera import PinholeCamera
from ..chunking import effective_chunk_elements
from .cost_volume import EpipolarRays, epipolar_rays, rows_per_chunk, sample_cost
from .descriptors import check_patch, gaussian_blur, patch_reach, stage_descriptors, zero_mean_basis
from .native_scores import native_coarse_scores
from .stage1 import best_fraction_mask, resolve_rule, stage1_mask
from .views import prepare_views

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MultiViewConfig:
    """Parameters of the semi-dense search (defaults for indoor scenes at 320x240)."""

    #: Nearest / farthest depth hypothesis (m); the sweep is uniform in inverse depth.
    min_depth: float = 0.2
    max_depth: float = 10.0
    #: Coarse inverse-depth samples per pixel.
    num_samples: int = 48
    #: Fine samples on each side of the coarse minimum (spacing = coarse step / refine_samples).
    refine_samples: int = 3
    #: Patch layout of the ZNCC cost ('cross' = 5 pixels, 'box' = 3x3) and its spacing (px).
    patch: str = 'box'
    patch_stride: int = 2
    #: Descriptor channels kept, lowest spatial frequencies first (0 = all: box 8, cross 4; exact ZNCC).
    descriptor_channels: int = 6
    #: Gaussian blur (px) before matching: less noise and aliasing along the sweep.
    blur_sigma: float = 0.5
    #: Grey-level noise floor of the ZNCC normalisation (texture below it matches nothing).
    noise_floor: float = 0.01
    #: Candidate pixels: grey gradient magnitude (grey levels per px, grey in [0, 1]) at least this.
    min_gradient: float = 0.02
    #: At most this fraction of the image is searched (the highest gradients win): bounds the time.
    max_candidate_fraction: float = 0.15
    #: Search every pixel instead of the high-gradient ones.
    all_pixels: bool = False
    #: A sample counts only if at least this fraction of the neighbours sees it (in image, in front).
    min_view_fraction: float = 0.5
    #: Estimates whose best cost (1 - ZNCC) is above this are dropped.
    max_cost: float = 0.5
    #: Samples around the best one ignored when looking for the second-best local minimum.
    second_min_exclusion: int = 2
    #: Stage-1 point selection: keep this fraction of the estimates, best score first.
    select_fraction: float = 0.25
    #: Largest intermediate tensor, in float elements (bounded memory, about 4 bytes each).
    chunk_elements: int = 1 << 22
    #: On a GPU, replay the sweep from a CUDA graph captured once per image size and neighbour
    #: count (``semidense_graph.py``): the same estimates, without the launch overhead.
    cuda_graph: bool = True

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad parameter."""
        if not (0 < self.min_depth < self.max_depth) or not math.isfinite(self.max_depth):
            raise ValueError(
                f'multi_view: need 0 < min_depth < max_depth, got {self.min_depth} and {self.max_depth}'
            )
        if self.num_samples < 3:
            raise ValueError(f'multi_view.num_samples must be >= 3, got {self.num_samples}')
        if self.refine_samples < 1:
            raise ValueError(f'multi_view.refine_samples must be >= 1, got {self.refine_samples}')
        check_patch(self.patch, self.patch_stride)
        zero_mean_basis(self.patch, self.descriptor_channels)  # raises on a bad channel count
        if not (0 < self.min_view_fraction <= 1):
            raise ValueError(f'multi_view.min_view_fraction must be in (0, 1], got {self.min_view_fraction}')
        if not (0 < self.select_fraction <= 1):
            raise ValueError(f'multi_view.select_fraction must be in (0, 1], got {self.select_fraction}')
        if not (0 < self.max_candidate_fraction <= 1):
            raise ValueError(
                f'multi_view.max_candidate_fraction must be in (0, 1], got {self.max_candidate_fraction}'
            )
        if self.chunk_elements < 1:
            raise ValueError(f'multi_view.chunk_elements must be positive, got {self.chunk_elements}')

    @property
    def rho_range(self) -> tuple[float, float]:
        return 1.0 / self.max_depth, 1.0 / self.min_depth


@dataclass
class MultiViewResult:
    """Semi-dense estimate of one keyframe; every map is (H, W) float32, NaN where no estimate."""

    depth: np.ndarray
    #: One pixel of matching error as a depth standard deviation (m).
    depth_std: np.ndarray
    #: ``distinctiveness * sharpness`` (the two factors are kept below for diagnostics).
    photometric_score: np.ndarray
    geometric_score: np.ndarray
    #: ``photometric_score * geometric_score``: what stage 1 ranks by.
    score: np.ndarray
    #: Best matching cost ``1 - ZNCC`` in [0, 2].
    cost: np.ndarray
    #: Pixels that were searched (bool).
    candidates: np.ndarray
    camera: PinholeCamera
    #: Modified second-best ratio ``1 - c1 / c2`` in [0, 1].
    distinctiveness: np.ndarray | None = None
    #: Cost curvature at the minimum per squared pixel of epipolar motion.
    sharpness: np.ndarray | None = None
    #: Frame indices of the neighbours used, when the caller knows them.
    neighbours: tuple[int, ...] = ()
    #: The method that produced it (``multi_view.method``): decides the stage-1 rule.
    method: ClassVar[str] = 'sweep'

    @property
    def valid(self) -> np.ndarray:
        """Pixels with an estimate."""
        return np.isfinite(self.depth)

    @property
    def density(self) -> float:
        """Fraction of the image with an estimate."""
        return float(self.valid.mean())

    def selected_mask(self, fraction: float = 0.25) -> np.ndarray:
        """Stage-1 selection: see :func:`select_best_fraction`."""
        return select_best_fraction(self, fraction)

    def stage1_mask(self, rule: str = 'auto', fraction: float = 0.25) -> np.ndarray:
        """Stage-1 points under ``rule`` (``auto``: this method's rule; see :mod:`.stage1`)."""
        return stage1_mask(self.depth, self.score, resolve_rule(rule, self.method), fraction)

    def selected_depth(self, fraction: float = 0.25) -> np.ndarray:
        """Depth of the stage-1 points, NaN elsewhere."""
        return np.where(self.selected_mask(fraction), self.depth, np.float32(np.nan)).astype(np.float32)


def select_best_fraction(result: MultiViewResult, fraction: float = 0.25) -> np.ndarray:
    """Stage 1 of the point selection (paper §III-D): the best ``fraction`` of the estimates by
    ``photometric x geometric`` score, as a bool mask. At least one point is kept when any exists."""
    return best_fraction_mask(result.depth, result.score, fraction)


def empty_result(camera: PinholeCamera) -> MultiViewResult:
    """A result without any estimate (e.g. a keyframe with no overlapping neighbour yet)."""
    nan = np.full((camera.height, camera.width), np.nan, dtype=np.float32)
    return MultiViewResult(
        depth=nan,
        depth_std=nan.copy(),
        photometric_score=nan.copy(),
        geometric_score=nan.copy(),
        score=nan.copy(),
        cost=nan.copy(),
        candidates=np.zeros(nan.shape, dtype=bool),
        camera=camera,
        distinctiveness=nan.copy(),
        sharpness=nan.copy(),
    )


def gradient_magnitude(gray: torch.Tensor) -> torch.Tensor:
    """Central-difference grey gradient magnitude (grey levels per pixel), zero on the border."""
    g = torch.zeros_like(gray)
    gx = (gray[1:-1, 2:] - gray[1:-1, :-2]) * 0.5
    gy = (gray[2:, 1:-1] - gray[:-2, 1:-1]) * 0.5
    g[1:-1, 1:-1] = torch.sqrt(gx * gx + gy * gy)
    return g


def candidate_margin(config: MultiViewConfig) -> int:
    """Pixels along the border that are never candidates: the patch's reach, plus one."""
    return patch_reach(config.patch, config.patch_stride) + 1


def candidate_mask(
    gray: torch.Tensor, config: MultiViewConfig, smooth: torch.Tensor | None = None
) -> torch.Tensor:
    """Pixels to search: high gradient (or all) and far enough from the border for the patch.

    ``smooth``: ``gray`` already blurred by ``config.blur_sigma``, when the caller has it."""
    h, w = gray.shape
    margin = candidate_margin(config)
    mask = torch.zeros((h, w), dtype=torch.bool, device=gray.device)
    if h <= 2 * margin or w <= 2 * margin:
        return mask
    if config.all_pixels:
        mask[margin:-margin, margin:-margin] = True
        return mask
    if smooth is None:
        smooth = gaussian_blur(gray[None], config.blur_sigma)[0]
    grad = gradient_magnitude(smooth)[margin:-margin, margin:-margin]
    threshold = config.min_gradient
    cap = int(config.max_candidate_fraction * h * w)
    if int((grad >= threshold).sum()) > cap:
        # The cap-th largest gradient: kthvalue (a selection) finds the same value several
        # times faster than topk's partial sort when the cap is a large fraction (the filter's 60 %).
        flat = grad.flatten()
        threshold = max(threshold, float(torch.kthvalue(flat, flat.numel() - max(cap, 1) + 1).values))
    mask[margin:-margin, margin:-margin] = grad >= threshold
    return mask


@dataclass
class _ChunkEstimate:
    rho: torch.Tensor
    cost: torch.Tensor
    distinct: torch.Tensor
    sharpness: torch.Tensor
    parallax_sq: torch.Tensor
    ok: torch.Tensor


def _gather(t: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return torch.gather(t, 1, idx[:, None])[:, 0]


def _coarse_scores(
    cost: torch.Tensor, count: torch.Tensor, need: float, exclusion: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Best cost and sample per row, and the modified second-best ratio ``1 - c1 / c2``, a
    sample's cost counting only where ``count >= need`` (else inf). On a CPU by a native kernel
    (``native_scores.py``: the same numbers in one pass a row), elsewhere by
    :func:`_coarse_scores_torch`."""
    scores = native_coarse_scores(cost, count, need, exclusion)
    if scores is not None:
        return scores
    return _coarse_scores_torch(torch.where(count >= need, cost, torch.full_like(cost, math.inf)), exclusion)


def _coarse_scores_torch(
    cost: torch.Tensor, exclusion: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_coarse_scores` of the cost with the unseen samples already set to inf, in torch."""
    c1, best = cost.min(dim=1)
    inf = torch.full_like(cost[:, :1], math.inf)
    left = torch.cat((inf, cost[:, :-1]), dim=1)
    right = torch.cat((cost[:, 1:], inf), dim=1)
    finite = torch.isfinite(cost)
    is_min = (cost <= left) & (cost <= right) & finite
    idx = torch.arange(cost.shape[1], device=cost.device)
    far = (idx[None, :] - best[:, None]).abs() > exclusion
    c2 = torch.where(is_min & far, cost, torch.full_like(cost, math.inf)).min(dim=1).values
    largest = torch.where(finite, cost, torch.full_like(cost, -math.inf)).max(dim=1).values
    c2 = torch.where(torch.isfinite(c2), c2, largest)
    distinct = torch.clamp(1.0 - c1 / torch.clamp(c2, min=1e-6), 0.0, 1.0)
    return c1, best, distinct


def _views_at(rays: EpipolarRays, rho: torch.Tensor, h: int, w: int, margin: float) -> torch.Tensor:
    u, v, in_front = rays.project(rho[:, None])
    return (in_front & (u >= margin) & (u <= w - 1 - margin) & (v >= margin) & (v <= h - 1 - margin))[..., 0]


def _search_chunk(
    key_desc: torch.Tensor,
    neighbour_desc: torch.Tensor,
    rays: EpipolarRays,
    rho_grid: torch.Tensor,
    config: MultiViewConfig,
    min_views: int,
    margin: float,
) -> _ChunkEstimate:
    """Coarse sweep, fine sweep and parabola for one chunk of pixels."""
    h, w = neighbour_desc.shape[-2:]
    need = min_views - 0.5  # counts are soft (bilinear visibility), so round
    cost, count = sample_cost(key_desc, neighbour_desc, rays, rho_grid)
    c1, best, distinct = _coarse_scores(cost, count, need, config.second_min_exclusion)
    samples = rho_grid.shape[0]
    ok = torch.isfinite(c1) & (best > 0) & (best < samples - 1)

    # Fine grid of 2R+1 samples spanning the coarse neighbours of the best sample.
    r = config.refine_samples
    step = (rho_grid[1] - rho_grid[0]) / r
    offsets = torch.arange(-r, r + 1, device=rho_grid.device, dtype=rho_grid.dtype) * step
    fine = rho_grid[best][:, None] + offsets[None, :]
    fcost, fcount = sample_cost(key_desc, neighbour_desc, rays, fine)
    fcost = torch.where(fcount >= need, fcost, torch.full_like(fcost, math.inf))
    j = fcost.argmin(dim=1).clamp(1, 2 * r - 1)
    cm, c0, cp = _gather(fcost, j - 1), _gather(fcost, j), _gather(fcost, j + 1)
    curvature = cm - 2.0 * c0 + cp
    ok &= torch.isfinite(curvature) & (curvature > 0)
    safe = torch.where(ok, curvature, torch.ones_like(curvature))
    delta = torch.clamp(0.5 * (cm - cp) / safe, -1.0, 1.0)
    rho = _gather(fine, j) + delta * step
    best_cost = c0 - 0.25 * (cm - cp) * delta

    visible = _views_at(rays, rho, h, w, margin)  # (n, M)
    parallax = rays.parallax(rho)
    parallax_sq = torch.where(visible, parallax * parallax, torch.zeros_like(parallax)).sum(dim=0)
    n_visible = visible.sum(dim=0)
    ok &= n_visible >= min_views
    # Curvature per squared pixel of epipolar motion (rms over the neighbours that see it).
    mean_sq = parallax_sq / n_visible.clamp(min=1)
    sharpness = torch.clamp(torch.where(ok, curvature, torch.zeros_like(curvature)) / (step * step), min=0.0)
    sharpness = torch.sqrt(torch.clamp(sharpness / torch.clamp(mean_sq, min=1e-12), max=4.0))
    rho_min, rho_max = config.rho_range
    ok &= (rho >= rho_min) & (rho <= rho_max) & (best_cost <= config.max_cost)
    return _ChunkEstimate(rho, best_cost, distinct, sharpness, parallax_sq, ok)


def estimate_semidense(
    key_gray: np.ndarray,
    key_pose: np.ndarray,
    neighbour_grays: Sequence[np.ndarray],
    neighbour_poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    config: MultiViewConfig | None = None,
    device: str | torch.device = 'cpu',
    neighbours: Sequence[int] = (),
) -> MultiViewResult:
    """Semi-dense depth of a keyframe from ``n >= 1`` posed neighbours.

    Images are grey (float32 in [0, 1], or uint8) at ``camera``'s size; poses camera-to-world
    4x4. Bad inputs raise ``ValueError`` (``geometry.PoseError`` for poses) naming the input.
    ``neighbours`` (frame indices) is only recorded in the result.
    """
    config = config or MultiViewConfig()
    config.validate()
    views = prepare_views(key_gray, key_pose, neighbour_grays, neighbour_poses, camera, device)
    dev = views.device
    n = views.num_neighbours
    min_views = max(1, math.ceil(config.min_view_fraction * n - 1e-9))
    if dev.type == 'cuda' and config.cuda_graph and not config.all_pixels:
        from .semidense_graph import estimate  # CUDA only

        graphed = estimate(views, config, min_views, tuple(int(i) for i in neighbours))
        if graphed is not None:
            return graphed
    margin = patch_reach(config.patch, config.patch_stride)
    desc = stage_descriptors(views.grays, config)
    channels = desc.shape[1] - 1
    cand = candidate_mask(views.grays[0], config)
    vs, us = torch.nonzero(cand, as_tuple=True)
    key_desc = desc[0, :channels][:, vs, us]
    neighbour_desc = desc[1:]
    rays = epipolar_rays(us.float(), vs.float(), camera.K, views.T_ok, camera.size, dev)
    rho_min, rho_max = config.rho_range
    rho_grid = torch.linspace(rho_min, rho_max, config.num_samples, device=dev, dtype=torch.float32)
    budget = effective_chunk_elements(config.chunk_elements, dev)
    chunk = rows_per_chunk(n, channels + 1, config.num_samples, budget)

    parts: list[_ChunkEstimate] = []
    with torch.no_grad():
        for start in range(0, int(vs.numel()), chunk):
            stop = min(start + chunk, int(vs.numel()))
            parts.append(
                _search_chunk(
                    key_desc[:, start:stop],
                    neighbour_desc,
                    rays.chunk(start, stop),
                    rho_grid,
                    config,
                    min_views,
                    float(margin),
                )
            )
    # One device-to-host copy of finished maps (each .cpu() is a synchronising round trip on CUDA).
    index = vs * camera.width + us
    every = torch.ones_like(index, dtype=torch.bool)  # every searched pixel is a candidate
    maps = result_maps(stacked_fields(parts, dev), index, every, camera.height, camera.width)
    result = result_from_maps(maps.cpu().numpy(), camera, tuple(int(i) for i in neighbours))
    log.debug(
        'semi-dense: %d candidates, %d estimates (%.1f %%), %d neighbours',
        int(vs.numel()),
        int(result.valid.sum()),
        100 * result.density,
        n,
    )
    return result


#: Fields of a searched pixel (``_ChunkEstimate``'s names).
FIELDS = ('rho', 'cost', 'distinct', 'sharpness', 'parallax_sq', 'ok')
#: The result's float maps, in the order :func:`result_maps` stacks them (the candidates follow).
RESULT_MAPS = (
    'depth',
    'depth_std',
    'photometric_score',
    'geometric_score',
    'score',
    'cost',
    'distinctiveness',
    'sharpness',
)


def stacked_fields(parts: list[_ChunkEstimate], device: torch.device) -> dict[str, torch.Tensor]:
    """Each :data:`FIELDS` over every chunk, in pixel order."""
    if not parts:
        return {
            n: torch.empty(0, dtype=torch.bool if n == 'ok' else torch.float32, device=device) for n in FIELDS
        }
    return {name: torch.cat([getattr(p, name) for p in parts]) for name in FIELDS}


def result_maps(
    fields: dict[str, torch.Tensor], index: torch.Tensor, candidate: torch.Tensor, h: int, w: int
) -> torch.Tensor:
    """The result's (H, W) maps (:data:`RESULT_MAPS`, NaN without an estimate; then the
    candidates, 1 or 0) from the fields of the searched pixels at flat ``index``.

    Built where the search ran: on a GPU the host then copies finished images once and
    scatters nothing; tensor ops only, so a CUDA graph can record it (``semidense_graph.py``).
    """
    ok = fields['ok'] & candidate
    rho = fields['rho']
    sigma_rho = 1.0 / torch.sqrt(fields['parallax_sq'].clamp(min=1e-24))
    photometric = fields['distinct'] * fields['sharpness']
    geometric = 1.0 / sigma_rho
    values = torch.stack(
        (
            1.0 / rho,
            sigma_rho / (rho * rho),
            photometric,
            geometric,
            photometric * geometric,
            fields['cost'],
            fields['distinct'],
            fields['sharpness'],
        )
    )
    n = len(RESULT_MAPS)
    maps = torch.full((n + 1, h * w), math.nan, dtype=torch.float32, device=rho.device)
    maps[:n].index_copy_(1, index, torch.where(ok, values, math.nan))
    maps[n] = 0.0
    maps[n].index_copy_(0, index, candidate.float())
    return maps.reshape(n + 1, h, w)


def result_from_maps(maps: np.ndarray, camera: PinholeCamera, neighbours: tuple[int, ...]) -> MultiViewResult:
    """The host copy of :func:`result_maps` as a result."""
    named = dict(zip(RESULT_MAPS, maps, strict=False))
    return MultiViewResult(
        **named, candidates=maps[len(RESULT_MAPS)] > 0.5, camera=camera, neighbours=neighbours
    )
