"""The semi-dense sweep as one CUDA graph per (image size, neighbour count, settings).

Why: on a GPU the sweep of a keyframe is ~900 op calls for about a millisecond of GPU work
(10.5 ms on an H200, docs/performance.md "GPU"); a graph launches them at once.

What makes it capturable: the eager sweep searches a data-dependent number of candidate
pixels (``nonzero`` of the gradient mask, with a threshold read back to the host). Here the
search runs on a fixed number of pixels instead: the ``max_candidate_fraction`` of the image
with the highest gradient (``topk``), of which those at or above the eager threshold
(``min_gradient``, or the cap-th largest gradient when more pixels pass it) are the
candidates. That is the eager candidate set, except where gradients tie exactly at the
threshold: the eager mask keeps every tied pixel, this one at most the cap. Each pixel's
search is independent of the others, so the estimates are the eager ones. Everything from
the descriptors to the result's images is recorded; one host copy of the images follows
the replay.

``all_pixels`` (a dense search, not the default) runs eagerly.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..camera import PinholeCamera
from ..chunking import effective_chunk_elements
from ..cuda_graph import GraphCache
from .cost_volume import EpipolarRays, gaussian_blur, patch_reach, rows_per_chunk, stage_descriptors
from .semidense import (
    MultiViewConfig,
    MultiViewResult,
    _search_chunk,
    gradient_magnitude,
)
from .views import Views

GRAPHS = GraphCache('semi-dense sweep')

#: Per-pixel fields of a searched pixel (``_ChunkEstimate``'s names).
FIELDS = ('rho', 'cost', 'distinct', 'sharpness', 'parallax_sq', 'ok')
#: The result's float maps, in the order :func:`search` stacks them (the candidates follow).
MAPS = (
    'depth',
    'depth_std',
    'photometric_score',
    'geometric_score',
    'score',
    'cost',
    'distinctiveness',
    'sharpness',
)


def candidate_capacity(config: MultiViewConfig, camera: PinholeCamera) -> int:
    """Pixels searched: the eager cap on candidates (``semidense.candidate_mask``)."""
    margin = patch_reach(config.patch, config.patch_stride) + 1
    interior = max(0, camera.height - 2 * margin) * max(0, camera.width - 2 * margin)
    return max(1, min(int(config.max_candidate_fraction * camera.height * camera.width), interior))


def top_candidates(gray: torch.Tensor, config: MultiViewConfig, capacity: int) -> tuple[torch.Tensor, ...]:
    """Flat indices of the ``capacity`` highest-gradient interior pixels and which are candidates.

    The eager rule (``semidense.candidate_mask``) on the device, without reading anything back.
    """
    h, w = gray.shape
    margin = patch_reach(config.patch, config.patch_stride) + 1
    smooth = gaussian_blur(gray[None], config.blur_sigma)[0]
    grad = torch.full((h, w), -math.inf, dtype=gray.dtype, device=gray.device)
    grad[margin:-margin, margin:-margin] = gradient_magnitude(smooth)[margin:-margin, margin:-margin]
    values, index = torch.topk(grad.flatten(), capacity)
    passing = (grad >= config.min_gradient).sum()
    cap = int(config.max_candidate_fraction * h * w)
    threshold = torch.where(passing > cap, values[-1].clamp(min=config.min_gradient), config.min_gradient)
    return index, values >= threshold


def search(
    grays: torch.Tensor,
    h_inf: torch.Tensor,
    b: torch.Tensor,
    config: MultiViewConfig,
    capacity: int,
    min_views: int,
) -> torch.Tensor:
    """The result's maps ``(len(MAPS) + 1, H, W)`` (:func:`result_maps`). No host
    synchronisation: capturable.

    ``h_inf`` (n, 3, 3) and ``b`` (n, 3) are ``epipolar_rays``' homography and ``K t_ok``.
    """
    n = h_inf.shape[0]
    h, w = grays.shape[-2:]
    desc = stage_descriptors(grays, config)
    channels = desc.shape[1] - 1
    index, candidate = top_candidates(grays[0], config, capacity)
    key_desc = desc[0, :channels].reshape(channels, -1)[:, index]
    pix = torch.stack(
        ((index % w).float(), (index // w).float(), torch.ones_like(index, dtype=torch.float32)), 1
    )
    rays = EpipolarRays(torch.einsum('nij,mj->nmi', h_inf, pix), b, w, h)
    rho_grid = torch.linspace(*config.rho_range, config.num_samples, device=grays.device, dtype=torch.float32)
    chunk = rows_per_chunk(
        n, channels + 1, config.num_samples, effective_chunk_elements(config.chunk_elements, grays.device)
    )
    margin = float(patch_reach(config.patch, config.patch_stride))
    parts = [
        _search_chunk(
            key_desc[:, s : s + chunk],
            desc[1:],
            rays.chunk(s, s + chunk),
            rho_grid,
            config,
            min_views,
            margin,
        )
        for s in range(0, capacity, chunk)
    ]
    fields = {name: torch.cat([getattr(p, name) for p in parts]) for name in FIELDS}
    return result_maps(fields, index, candidate, h, w)


def result_maps(
    fields: dict[str, torch.Tensor], index: torch.Tensor, candidate: torch.Tensor, h: int, w: int
) -> torch.Tensor:
    """The result's (H, W) maps (:data:`MAPS`, NaN without an estimate; the candidates 1 or 0)
    from the fields of the searched pixels at flat ``index``, built on the device: one copy
    to the host of finished images, no scatter there (``semidense.result_from_fields``, in float32)."""
    ok = fields['ok'] & candidate
    rho = fields['rho']
    sigma_rho = torch.rsqrt(fields['parallax_sq'].clamp(min=1e-24))
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
    maps = torch.full((len(MAPS) + 1, h * w), math.nan, dtype=torch.float32, device=rho.device)
    maps[: len(MAPS)].index_copy_(1, index, torch.where(ok, values, math.nan))
    maps[len(MAPS)] = 0.0
    maps[len(MAPS)].index_copy_(0, index, candidate.float())
    return maps.reshape(len(MAPS) + 1, h, w)


def epipolar_inputs(views: Views) -> tuple[torch.Tensor, torch.Tensor]:
    """``epipolar_rays``' per-neighbour homography at infinity and ``K t_ok``, on the device."""
    K = np.asarray(views.camera.K, dtype=np.float64)
    T_ok = np.asarray(views.T_ok, dtype=np.float64).reshape(-1, 4, 4)
    h_inf = K @ T_ok[:, :3, :3] @ np.linalg.inv(K)
    b = np.einsum('ij,nj->ni', K, T_ok[:, :3, 3])
    return (
        torch.as_tensor(h_inf, dtype=torch.float32, device=views.device),
        torch.as_tensor(b, dtype=torch.float32, device=views.device),
    )


def unpack(maps: np.ndarray, camera: PinholeCamera, neighbours: tuple[int, ...]) -> MultiViewResult:
    """The host copy of :func:`search`'s maps as the eager sweep's result."""
    named = dict(zip(MAPS, maps, strict=False))
    return MultiViewResult(**named, candidates=maps[len(MAPS)] > 0.5, camera=camera, neighbours=neighbours)


def estimate(
    views: Views, config: MultiViewConfig, min_views: int, neighbours: tuple[int, ...], graph: bool = True
) -> MultiViewResult | None:
    """The sweep of ``views`` replayed from its CUDA graph (``graph``; else run eagerly, the same
    code), or None when capturing failed: the caller then runs the eager sweep."""
    camera = views.camera
    capacity = candidate_capacity(config, camera)
    h_inf, b = epipolar_inputs(views)

    def sweep(grays: torch.Tensor, h_inf: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return search(grays, h_inf, b, config, capacity, min_views)

    with torch.no_grad():
        if graph:
            key = (views.device, tuple(views.grays.shape), config, min_views)
            out = GRAPHS.run(key, sweep, (views.grays, h_inf, b))
            if out is None:
                return None
            packed = out[0]
        else:
            packed = sweep(views.grays, h_inf, b)
    return unpack(packed.cpu().numpy(), camera, neighbours)
