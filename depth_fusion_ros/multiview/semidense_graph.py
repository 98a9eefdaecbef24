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

import torch

from ..camera import PinholeCamera
from ..chunking import effective_chunk_elements
from ..cuda_graph import GraphCache
from .cost_volume import epipolar_matrices, rays_from, rows_per_chunk
from .descriptors import gaussian_blur, patch_reach, stage_descriptors
from .semidense import (
    MultiViewConfig,
    MultiViewResult,
    _search_chunk,
    candidate_margin,
    gradient_magnitude,
    result_from_maps,
    result_maps,
    stacked_fields,
)
from .views import Views

GRAPHS = GraphCache('semi-dense sweep')


def candidate_capacity(config: MultiViewConfig, camera: PinholeCamera) -> int:
    """Pixels searched: the eager cap on candidates (``semidense.candidate_mask``)."""
    margin = candidate_margin(config)
    interior = max(0, camera.height - 2 * margin) * max(0, camera.width - 2 * margin)
    return max(1, min(int(config.max_candidate_fraction * camera.height * camera.width), interior))


def top_candidates(gray: torch.Tensor, config: MultiViewConfig, capacity: int) -> tuple[torch.Tensor, ...]:
    """Flat indices of the ``capacity`` highest-gradient interior pixels and which are candidates.

    The eager rule (``semidense.candidate_mask``) on the device, without reading anything back.
    """
    h, w = gray.shape
    margin = candidate_margin(config)
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
    """The result's maps (``semidense.result_maps``). No host synchronisation: capturable.

    ``h_inf`` (n, 3, 3) and ``b`` (n, 3) are ``epipolar_rays``' homography and ``K t_ok``.
    """
    n = h_inf.shape[0]
    h, w = grays.shape[-2:]
    desc = stage_descriptors(grays, config)
    channels = desc.shape[1] - 1
    index, candidate = top_candidates(grays[0], config, capacity)
    key_desc = desc[0, :channels].reshape(channels, -1)[:, index]
    rays = rays_from(h_inf, b, (index % w).float(), (index // w).float(), (w, h))
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
    return result_maps(stacked_fields(parts, grays.device), index, candidate, h, w)


def estimate(
    views: Views, config: MultiViewConfig, min_views: int, neighbours: tuple[int, ...], graph: bool = True
) -> MultiViewResult | None:
    """The sweep of ``views`` replayed from its CUDA graph (``graph``; else run eagerly, the same
    code), or None when capturing failed: the caller then runs the eager sweep."""
    camera = views.camera
    capacity = candidate_capacity(config, camera)
    h_inf, b = epipolar_matrices(camera.K, views.T_ok, views.device)

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
    return result_from_maps(packed.cpu().numpy(), camera, neighbours)
