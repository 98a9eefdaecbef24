"""Photometric matching cost of keyframe pixels against neighbour frames at hypothesised inverse depths.

This is the shared core of the semi-dense search (``semidense.py``) and of the dense TV
baseline (``tv.py``): both need ``C(x, rho)``, the photometric error of keyframe pixel ``x``
at inverse depth ``rho`` averaged over the neighbours that see it.

Inverse depth is the inverse **z-depth** (``rho = 1 / z``, the SPEC's ``m = 1 / rho``), not the
inverse distance along the unit ray of the paper's eq. (1): with ``x_n = K^-1 (u, v, 1)`` the
keyframe point is ``x_n / rho`` and its projection into a neighbour is

    p_o(rho) ~ K (R_ok x_n + rho t_ok) = a + rho b,   u_o = (a_0 + rho b_0) / (a_2 + rho b_2),

a ratio of affine functions of ``rho``. ``a`` (per pixel and neighbour) and ``b`` (per
neighbour) are computed once, so a sweep over any number of samples is a few multiply-adds
followed by one bilinear gather (``grid_sample``) for all pixels x samples x neighbours.

Photometric error: ``1 - ZNCC`` of a small patch, a dot product of the per-pixel patch
descriptors of ``descriptors.py`` (why ZNCC, and how a patch becomes a descriptor, is there):
a bilinear lookup of the neighbour's descriptor image at the projected point gives its
normalised patch there.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .. import vml_warmup  # noqa: F401  (MKL VML dispatch resolved before the first parallel sqrt)
from .native_cost import native_sweep_cost


@functools.lru_cache(maxsize=16)
def _grid_scale(width: int, height: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Pixel to ``grid_sample`` scale per coordinate, made once per size and device: a tensor
    from host data is a copy, which a CUDA graph cannot record (``cuda_graph.py``)."""
    return torch.tensor([2.0 / (width - 1), 2.0 / (height - 1), 1.0], dtype=dtype, device=device)


@dataclass
class EpipolarRays:
    """Projection of keyframe pixels into ``n`` neighbours as affine functions of inverse depth.

    ``a`` (n, M, 3) = ``K R_ok x_n`` per neighbour and pixel, ``b`` (n, 3) = ``K t_ok``, so the
    homogeneous projection at inverse depth ``rho`` is ``a + rho b``. ``width``/``height`` are
    the neighbour image size (for the normalised coordinates of ``grid_sample``).
    """

    a: torch.Tensor
    b: torch.Tensor
    width: int
    height: int

    @property
    def num_neighbours(self) -> int:
        return int(self.b.shape[0])

    def chunk(self, start: int, stop: int) -> EpipolarRays:
        return EpipolarRays(self.a[:, start:stop], self.b, self.width, self.height)

    def _normalised(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``a``, ``b`` rescaled so ``(a + rho b)[:2] / (a + rho b)[2]`` is ``grid_sample``'s [-1, 1].

        ``x = u * 2 / (W - 1) - 1 = (sx num_u - w) / w``: folding the affine map into the
        rows costs O(M) instead of O(M x S) per sweep.
        """
        scale = _grid_scale(self.width, self.height, self.a.dtype, self.a.device)
        a = self.a * scale
        b = self.b * scale
        a = torch.cat((a[..., :2] - a[..., 2:], a[..., 2:]), dim=-1)
        b = torch.cat((b[..., :2] - b[..., 2:], b[..., 2:]), dim=-1)
        return a, b

    def grid(self, rho: torch.Tensor) -> torch.Tensor:
        """``grid_sample`` coordinates (n, M, S, 2) at inverse depths ``rho`` ((S,) or (M, S)).

        Points behind a neighbour camera are sent far outside its image (they sample zeros):
        ``w`` is clamped to a small positive value, which no visible point has (``w`` is about 1).
        """
        a, b = self._normalised()
        rho = rho if rho.ndim == 2 else rho[None, :]
        n, m = a.shape[:2]
        s = rho.shape[-1]
        out = torch.empty((n, m, s, 2), dtype=a.dtype, device=a.device)
        w = torch.addcmul(a[..., 2:3], b[:, None, 2:3], rho[None]).clamp_(min=1e-4)
        for k in range(2):
            torch.div(torch.addcmul(a[..., k : k + 1], b[:, None, k : k + 1], rho[None]), w, out=out[..., k])
        return out

    def project(self, rho: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel ``(u, v)`` (n, M, S) at inverse depths ``rho`` ((S,) or (M, S)), and whether the
        point lies in front of the neighbour camera."""
        rho = rho if rho.ndim == 2 else rho[None, :]
        a = self.a[..., None]  # (n, M, 3, 1)
        b = self.b[:, None, :, None]  # (n, 1, 3, 1)
        p = a + b * rho[None, :, None, :]  # (n, M, 3, S)
        w = p[:, :, 2]
        in_front = w > 1e-9
        w_safe = torch.where(in_front, w, torch.ones_like(w))
        return p[:, :, 0] / w_safe, p[:, :, 1] / w_safe, in_front

    def motion(self, rho: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(du/drho, dv/drho)`` (n, M) at inverse depths ``rho`` (M,): the epipolar direction
        scaled by the pixels moved per unit inverse depth.

        From ``u = (a0 + rho b0) / (a2 + rho b2)``: ``du/drho = (b0 a2 - a0 b2) / (a2 + rho b2)^2``.
        """
        return epipolar_motion(self.a.unbind(-1), self.b[:, None, :].unbind(-1), rho[None, :])

    def parallax(self, rho: torch.Tensor) -> torch.Tensor:
        """``|d p_o / d rho|`` (n, M): pixels moved along each epipolar line per unit inverse depth.

        Zero for a pure rotation (``t_ok = 0``), which is what makes its geometric score 0.
        """
        du, dv = self.motion(rho)
        return torch.sqrt(du * du + dv * dv)


def epipolar_motion(
    a: Sequence[torch.Tensor], b: Sequence[torch.Tensor | float], rho: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(du/drho, dv/drho)`` of homogeneous projections ``a + rho b``, given by their three
    coordinates (``a0, a1, a2`` and ``b0, b1, b2`` broadcasting with ``rho``; ``b``'s may be
    numbers): :meth:`EpipolarRays.motion` and the filter's per-row motion."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    w = a2 + rho * b2
    w2 = torch.clamp(w * w, min=1e-12)
    du = (b0 * a2 - a0 * b2) / w2
    dv = (b1 * a2 - a1 * b2) / w2
    return du, dv


def epipolar_matrices(
    K: np.ndarray, T_ok: np.ndarray, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per neighbour, the pixel-to-pixel homography at infinity ``K R_ok K^-1`` (n, 3, 3) and
    ``K t_ok`` (n, 3), for relative poses ``T_ok`` (n, 4, 4), on ``device``."""
    K = np.asarray(K, dtype=np.float64)
    T_ok = np.asarray(T_ok, dtype=np.float64).reshape(-1, 4, 4)
    H = K @ T_ok[:, :3, :3] @ np.linalg.inv(K)
    b = np.einsum('ij,nj->ni', K, T_ok[:, :3, 3])
    return (
        torch.as_tensor(H, dtype=torch.float32, device=device),
        torch.as_tensor(b, dtype=torch.float32, device=device),
    )


def rays_from(
    h_inf: torch.Tensor, b: torch.Tensor, u: torch.Tensor, v: torch.Tensor, size: tuple[int, int]
) -> EpipolarRays:
    """Rays of keyframe pixels ``(u, v)`` (M,) from :func:`epipolar_matrices`; ``size`` = (W, H).
    Tensor ops only (no host copy): a CUDA graph can record it (``semidense_graph.py``)."""
    pix = torch.stack((u, v, torch.ones_like(u)), dim=-1).to(
        device=h_inf.device, dtype=torch.float32
    )  # (M, 3)
    a = torch.einsum('nij,mj->nmi', h_inf, pix)
    return EpipolarRays(a, b, int(size[0]), int(size[1]))


def epipolar_rays(
    u: torch.Tensor,
    v: torch.Tensor,
    K: np.ndarray,
    T_ok: np.ndarray,
    size: tuple[int, int],
    device: torch.device,
) -> EpipolarRays:
    """Rays of keyframe pixels ``(u, v)`` (M,) for relative poses ``T_ok`` (n, 4, 4); ``size`` = (W, H)."""
    return rays_from(*epipolar_matrices(K, T_ok, device), u, v, size)


def sample_cost(
    key_desc: torch.Tensor, neighbour_images: torch.Tensor, rays: EpipolarRays, rho: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`sample_cost_torch`'s cost and count; on a CPU by the native kernel
    (``native_cost.py``: the same numbers in one pass), elsewhere or where that cannot run by
    the torch code."""
    if neighbour_images.device.type == 'cpu':
        a, b = rays._normalised()
        native = native_sweep_cost(key_desc, neighbour_images, a, b, rho)
        if native is not None:
            return native
    return sample_cost_torch(key_desc, neighbour_images, rays, rho)


def sample_cost_torch(
    key_desc: torch.Tensor, neighbour_images: torch.Tensor, rays: EpipolarRays, rho: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour-averaged ``1 - ZNCC`` (M, S) and the (soft) number of neighbours seeing each sample.

    ``key_desc`` (C, M) are the keyframe descriptors of the M pixels, ``neighbour_images``
    (n, C + 1, H, W) the neighbour descriptors with their visibility channel
    (``patch_descriptors(..., visibility_margin=...)``). Sampling that channel bilinearly gives,
    at once with the descriptor, the (soft) weight of each neighbour for each sample: 1 well
    inside the image, 0 outside or behind the camera (zero padding), a fraction on the border,
    with no per-sample masks to compute. Where no neighbour sees a sample the mean is 1 (no
    match) and the count 0; callers decide how many views they require.
    """
    channels = key_desc.shape[0]
    sampled = F.grid_sample(
        neighbour_images, rays.grid(rho), mode='bilinear', padding_mode='zeros', align_corners=True
    )  # (n, C + 1, M, S)
    summed = sampled.sum(dim=0)  # (C + 1, M, S): the key descriptor is the same for every neighbour
    count = summed[channels]
    zncc = summed[:channels].mul_(key_desc[:, :, None]).sum(dim=0)  # in place: fewer buffers
    cost = zncc.neg_().add_(count).add_(1e-3).div_(count + 1e-3)  # (count - zncc + 1e-3) / (count + 1e-3)
    return cost, count


def rows_per_chunk(num_neighbours: int, channels: int, samples: int, budget_elements: int) -> int:
    """Pixels per chunk so the largest intermediate (n x C x M x S floats) stays within budget."""
    per_row = max(1, num_neighbours * max(channels, 3) * samples)
    return max(1, int(budget_elements) // per_row)
