"""DTAM-style dense multi-view depth: cost volume + Huber-TV regularisation (the paper's "TV" baseline).

Newcombe et al., "DTAM: Dense Tracking and Mapping in Real-Time" (ICCV 2011), with the
primal-dual algorithm of Handa et al., "Applications of Legendre-Fenchel transformation to
computer vision problems" (2011 tech. report):

1. a photometric cost volume ``C(x, k)`` for *every* pixel and ``num_samples`` inverse depths
   (the same ``1 - ZNCC`` cost and neighbours as the semi-dense search, ``cost_volume.py``);
2. minimise ``E(d) = sum_x g(x) |grad d(x)|_eps + lambda C(x, d(x))`` over the normalised
   inverse depth ``d`` in [0, 1] (``rho = rho_min + d (rho_max - rho_min)``), where ``|.|_eps``
   is the Huber norm and ``g = exp(-alpha |grad I|^beta)`` lowers the smoothing across image
   edges. The non-convex data term is decoupled through an auxiliary ``a`` and a quadratic
   coupling ``(d - a)^2 / (2 theta)``: for a fixed ``a`` the convex Huber-ROF problem in ``d``
   takes one primal-dual step (dual ascent on ``q``, projected on the unit ball; primal descent
   on ``d``); for a fixed ``d`` the point-wise problem in ``a`` is an exhaustive search over the
   samples of the cost volume refined by a parabola. ``theta`` decreases geometrically from
   ``theta_start`` to ``theta_end``, which tightens the coupling until ``d = a``.

Inverse depth is inverse z-depth; the output is dense (every pixel has a depth). Memory:
the cost volume is ``H x W x num_samples`` float32 (20 MB at 320x240x64); it is built in
chunks of pixels, so the intermediate tensors stay bounded by ``chunk_elements``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..camera import PinholeCamera
from ..chunking import effective_chunk_elements
from ..compile_lock import compile_serialised
from .cost_volume import epipolar_rays, rows_per_chunk, sample_cost
from .descriptors import check_patch, gaussian_blur, stage_descriptors, zero_mean_basis
from .views import prepare_views

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TVConfig:
    """Parameters of the TV-regularised dense baseline (DTAM defaults where they apply)."""

    #: Depth range (m) and inverse-depth samples of the cost volume.
    min_depth: float = 0.2
    max_depth: float = 10.0
    num_samples: int = 64
    #: Patch of the ZNCC cost (see ``MultiViewConfig``).
    patch: str = 'box'
    patch_stride: int = 2
    descriptor_channels: int = 0
    blur_sigma: float = 0.5
    noise_floor: float = 0.01
    #: A cost sample counts only if at least this fraction of the neighbours sees it.
    min_view_fraction: float = 0.5
    #: Weight of the photometric data term against the TV term.
    data_weight: float = 1.0
    #: Weight each pixel's data term by its cost curve's contrast (see ``data_confidence``).
    confidence_weighting: bool = True
    #: Pixels below this confidence start from the median confident inverse depth.
    min_confidence: float = 0.1
    #: Huber threshold of the regulariser (normalised inverse depth per pixel).
    huber_eps: float = 1e-3
    #: Edge weight ``g = exp(-edge_alpha |grad I|^edge_beta)`` (grey in [0, 1] per pixel).
    edge_alpha: float = 10.0
    edge_beta: float = 1.0
    #: Coupling schedule: ``theta`` from ``theta_start`` to ``theta_end``, times ``theta_decay`` per step.
    theta_start: float = 0.2
    theta_end: float = 1e-4
    theta_decay: float = 0.85
    #: Largest intermediate tensor while building the cost volume, in float elements.
    chunk_elements: int = 1 << 22
    #: On a GPU, replay the iterations from one captured CUDA graph (``tv_graph.py``).
    cuda_graph: bool = True

    def validate(self) -> None:
        if not (0 < self.min_depth < self.max_depth) or not math.isfinite(self.max_depth):
            raise ValueError(f'tv: need 0 < min_depth < max_depth, got {self.min_depth} and {self.max_depth}')
        if self.num_samples < 3:
            raise ValueError(f'tv.num_samples must be >= 3, got {self.num_samples}')
        check_patch(self.patch, self.patch_stride)
        zero_mean_basis(self.patch, self.descriptor_channels)
        if not (0 < self.theta_end < self.theta_start):
            raise ValueError(
                f'tv: need 0 < theta_end < theta_start, got {self.theta_end}, {self.theta_start}'
            )
        if not (0 < self.theta_decay < 1):
            raise ValueError(f'tv.theta_decay must be in (0, 1), got {self.theta_decay}')
        if self.data_weight <= 0 or self.huber_eps < 0:
            raise ValueError('tv.data_weight must be positive and tv.huber_eps non-negative')

    @property
    def rho_range(self) -> tuple[float, float]:
        return 1.0 / self.max_depth, 1.0 / self.min_depth

    @property
    def iterations(self) -> int:
        """Primal-dual iterations the ``theta`` schedule implies."""
        return max(1, math.ceil(math.log(self.theta_end / self.theta_start) / math.log(self.theta_decay)))


def build_cost_volume(
    grays: torch.Tensor, T_ok: np.ndarray, camera: PinholeCamera, config: TVConfig
) -> torch.Tensor:
    """``(H*W, S)`` mean ``1 - ZNCC`` of every keyframe pixel at ``num_samples`` inverse depths.

    Samples seen by too few neighbours get the uninformative cost 1, so the regulariser
    fills them in.
    """
    device = grays.device
    h, w = camera.height, camera.width
    desc = stage_descriptors(grays, config)
    channels = desc.shape[1] - 1
    neighbour_images = desc[1:]
    key_desc = desc[0, :channels].reshape(channels, -1)
    v, u = torch.meshgrid(
        torch.arange(h, device=device, dtype=torch.float32),
        torch.arange(w, device=device, dtype=torch.float32),
        indexing='ij',
    )
    rays = epipolar_rays(u.reshape(-1), v.reshape(-1), camera.K, T_ok, camera.size, device)
    rho = torch.linspace(*config.rho_range, config.num_samples, device=device)
    n = T_ok.shape[0]
    need = max(1, math.ceil(config.min_view_fraction * n - 1e-9)) - 0.5
    budget = effective_chunk_elements(config.chunk_elements, key_desc.device)
    chunk = rows_per_chunk(n, channels + 1, config.num_samples, budget)
    volume = torch.empty((h * w, config.num_samples), dtype=torch.float32, device=device)
    for start in range(0, h * w, chunk):
        stop = min(start + chunk, h * w)
        cost, count = sample_cost(key_desc[:, start:stop], neighbour_images, rays.chunk(start, stop), rho)
        volume[start:stop] = torch.where(count >= need, cost, torch.ones_like(cost))
    return volume


def edge_weights(gray: torch.Tensor, alpha: float, beta: float) -> torch.Tensor:
    """``g = exp(-alpha |grad I|^beta)``: small across strong image edges, where depth may jump."""
    gy, gx = torch.gradient(gray)
    return torch.exp(-alpha * torch.sqrt(gx * gx + gy * gy).pow(beta))


def _grad(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences with Neumann boundary (zero past the last row/column)."""
    gx = torch.zeros_like(d)
    gy = torch.zeros_like(d)
    gx[:, :-1] = d[:, 1:] - d[:, :-1]
    gy[:-1, :] = d[1:, :] - d[:-1, :]
    return gx, gy


def _div(px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Divergence, the negative adjoint of :func:`_grad`."""
    div = torch.zeros_like(px)
    div[:, 0] = px[:, 0]
    div[:, 1:-1] = px[:, 1:-1] - px[:, :-2]
    div[:, -1] = -px[:, -2]
    div[0, :] += py[0, :]
    div[1:-1, :] += py[1:-1, :] - py[:-2, :]
    div[-1, :] += -py[-2, :]
    return div


def window_radius(theta: float, cost_range: float, samples: int) -> int:
    """Half-width (samples) of the point search's window at ``theta``: DTAM's search-window bound.

    Only samples with ``(d - a)^2 / (2 theta) <= cost_range`` can win; one sample of slack on
    each side, and one more so the parabola needs no second lookup.
    """
    return math.ceil(math.sqrt(2.0 * theta * cost_range) * (samples - 1)) + 2


def _point_search(weighted: torch.Tensor, d: torch.Tensor, theta: float, radius: int) -> torch.Tensor:
    """``argmin_a (d - a)^2 / (2 theta) + w C(a)`` per pixel, refined by a parabola.

    ``weighted`` is the (H*W, S) volume already multiplied by the per-pixel data weight ``w``;
    ``radius`` the window's half-width (:func:`window_radius`): the search looks at a window
    around ``d`` that shrinks with ``theta``, so the late iterations cost a few samples
    instead of the whole volume. Every tensor it makes comes from a kernel (no host copy), so
    the loop can be captured in a CUDA graph (``tv_graph.py``).
    """
    n, s = weighted.shape
    scale = 1.0 / (s - 1)
    pos = d.reshape(-1) * (s - 1)  # continuous sample index of d
    if 2 * radius + 1 >= s:  # the whole volume: no gather needed
        start = torch.zeros(n, dtype=torch.long, device=d.device)
        offsets = torch.arange(s, device=d.device)
        costs = weighted
    else:
        start = torch.round(pos).long() - radius
        offsets = torch.arange(2 * radius + 1, device=d.device)
        costs = torch.gather(weighted, 1, (start[:, None] + offsets[None, :]).clamp_(0, s - 1))
    # Out-of-range window entries repeat a border sample with a larger quadratic term: they never win.
    quad = ((pos - start)[:, None] - offsets[None, :]) * scale
    energy = torch.addcmul(costs, quad, quad, value=0.5 / theta)
    j = energy[:, 1:-1].argmin(dim=1, keepdim=True) + 1
    around = torch.arange(-1, 2, device=d.device)[None, :]
    e_m, e_0, e_p = torch.gather(energy, 1, j + around).unbind(dim=1)
    curvature = e_m - 2.0 * e_0 + e_p
    delta = torch.where(
        curvature > 1e-12, 0.5 * (e_m - e_p) / curvature.clamp(min=1e-12), torch.zeros_like(e_0)
    )
    a = ((start + j[:, 0]).to(d.dtype) + delta.clamp(-1.0, 1.0)) * scale
    return a.reshape(d.shape).clamp(0.0, 1.0)


def data_confidence(volume: torch.Tensor) -> torch.Tensor:
    """``(mean C - min C) / mean C`` per pixel (H*W, 1): 0 for a flat cost curve (no texture).

    Weighting the data term by it lets the regulariser alone fill texture-less areas, where a
    normalised cost is pure noise and its minimum random; plain DTAM trusts every pixel's
    cost equally and needs far more iterations to smooth such noise out.
    """
    mean = volume.mean(dim=1, keepdim=True)
    return ((mean - volume.min(dim=1, keepdim=True).values) / mean.clamp(min=1e-6)).clamp(0.0, 1.0)


def _primal_dual_step(
    qx: torch.Tensor,
    qy: torch.Tensor,
    d: torch.Tensor,
    a: torch.Tensor,
    g: torch.Tensor,
    sigma_q: float,
    tau_d: float,
    eps: float,
    theta: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One Chambolle-Pock iteration of the Huber-TV problem coupled to ``a``: dual ascent on
    ``q`` (projected on the unit ball), then primal descent on ``d``."""
    gx, gy = _grad(d)
    qx = (qx + sigma_q * g * gx) / (1.0 + sigma_q * eps)
    qy = (qy + sigma_q * g * gy) / (1.0 + sigma_q * eps)
    norm = torch.clamp(torch.sqrt(qx * qx + qy * qy), min=1.0)
    qx, qy = qx / norm, qy / norm
    d = (d + tau_d * (g * _div(qx, qy) + a / theta)) / (1.0 + tau_d / theta)
    return qx, qy, d


_COMPILED_STEP: dict[str, Callable] = {}


def _primal_dual_step_for(device: torch.device) -> Callable:
    """The iteration as one fused kernel on a GPU (``torch.compile``; ~25 launches otherwise,
    which dominate there), eager on a CPU. Falls back to eager, logged once, if compiling fails."""
    if device.type == 'cpu' or _COMPILED_STEP.get(device.type) is False:
        return _primal_dual_step
    if device.type not in _COMPILED_STEP:
        _COMPILED_STEP[device.type] = compile_serialised(_primal_dual_step, dynamic=False)
    compiled = _COMPILED_STEP[device.type]

    def guarded(*args: object) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if _COMPILED_STEP.get(device.type) is False:
            return _primal_dual_step(*args)
        try:
            return compiled(*args)
        except Exception as exc:  # the compiler stack raises many types; any failure means eager
            _COMPILED_STEP[device.type] = False
            log.warning('torch.compile of the TV iteration failed on %s (%s); using eager', device, exc)
            return _primal_dual_step(*args)

    return guarded


def theta_schedule(config: TVConfig) -> list[float]:
    """``theta`` of each iteration: geometric from ``theta_start`` down to ``theta_end``."""
    thetas, theta = [], config.theta_start
    for _ in range(config.iterations):
        thetas.append(theta)
        theta = max(theta * config.theta_decay, config.theta_end)
    return thetas


def iterate(
    weighted: torch.Tensor,
    g: torch.Tensor,
    a: torch.Tensor,
    config: TVConfig,
    radii: Sequence[int],
    theta_t: torch.Tensor | None = None,
) -> torch.Tensor:
    """The coupled iterations from the start ``a``: one primal-dual step, one point search each.

    ``radii`` are the point search's windows, one per iteration (:func:`window_radius`);
    ``theta_t`` the schedule on the device (made here when None). Given ``theta_t``, it makes
    no host copy or synchronisation and its shapes are fixed by the inputs and ``radii``:
    capturable as one CUDA graph.
    """
    d = a.clone()
    qx = torch.zeros_like(d)
    qy = torch.zeros_like(d)
    # Chambolle-Pock steps with sigma * tau * L^2 <= 1 for the weighted gradient (L^2 = 8 max g^2 <= 8).
    sigma_q = tau_d = 1.0 / math.sqrt(8.0)
    thetas = theta_schedule(config)
    if theta_t is None:  # theta as a 0-d tensor each: a compiled step must not be specialised per value
        theta_t = torch.tensor(thetas, dtype=d.dtype, device=d.device)
    step = _primal_dual_step_for(weighted.device)
    for i, (theta, radius) in enumerate(zip(thetas, radii, strict=True)):
        qx, qy, d = step(qx, qy, d, a, g, sigma_q, tau_d, config.huber_eps, theta_t[i])
        a = _point_search(weighted, d, theta, radius)
    return a


def _start(volume: torch.Tensor, gray: torch.Tensor, config: TVConfig) -> tuple[torch.Tensor, ...]:
    """Edge weights ``g``, the weighted volume and the start ``a`` (each pixel's best sample)."""
    h, w = gray.shape
    g = edge_weights(gaussian_blur(gray[None], config.blur_sigma)[0], config.edge_alpha, config.edge_beta)
    s = volume.shape[1]
    a = (volume.argmin(dim=1).to(torch.float32) / (s - 1)).reshape(h, w)
    weight = torch.full((h * w, 1), config.data_weight, device=volume.device)
    if config.confidence_weighting:
        confidence = data_confidence(volume)
        weight = weight * confidence
        # Start texture-less pixels at the typical confident inverse depth, not at a random minimum.
        low = (confidence < config.min_confidence).reshape(h, w)
        if bool(low.any()) and not bool(low.all()):
            a = torch.where(low, a[~low].median(), a)
    return g, volume * weight, a


def regularise(volume: torch.Tensor, gray: torch.Tensor, config: TVConfig) -> torch.Tensor:
    """Normalised inverse depth ``d`` (H, W) in [0, 1] minimising the decoupled Huber-TV energy.

    On a GPU the iterations are replayed from a CUDA graph (``config.cuda_graph``,
    ``tv_graph.py``); elsewhere, and if capturing fails, they run eagerly.
    """
    g, weighted, a = _start(volume, gray, config)
    if weighted.device.type == 'cuda' and config.cuda_graph:
        from .tv_graph import run_graphed  # CUDA only

        graphed = run_graphed(weighted, g, a, config)
        if graphed is not None:
            return graphed
    cost_range = float((weighted.max(dim=1).values - weighted.min(dim=1).values).max())
    s = volume.shape[1]
    radii = [window_radius(theta, cost_range, s) for theta in theta_schedule(config)]
    return iterate(weighted, g, a, config, radii)


def estimate_tv(
    key_gray: np.ndarray,
    key_pose: np.ndarray,
    neighbour_grays: Sequence[np.ndarray],
    neighbour_poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    config: TVConfig | None = None,
    device: str | torch.device = 'cpu',
) -> np.ndarray:
    """Dense depth (H, W) float32 in metres of a keyframe from ``n >= 1`` posed neighbours.

    Same inputs and errors as :func:`~.semidense.estimate_semidense`.
    """
    config = config or TVConfig()
    config.validate()
    views = prepare_views(key_gray, key_pose, neighbour_grays, neighbour_poses, camera, device)
    with torch.no_grad():
        volume = build_cost_volume(views.grays, views.T_ok, camera, config)
        d = regularise(volume, views.grays[0], config)
    rho_min, rho_max = config.rho_range
    rho = rho_min + d * (rho_max - rho_min)
    log.debug(
        'tv: %d iterations, %d samples, %d neighbours',
        config.iterations,
        config.num_samples,
        views.num_neighbours,
    )
    return (1.0 / rho).cpu().numpy().astype(np.float32)
