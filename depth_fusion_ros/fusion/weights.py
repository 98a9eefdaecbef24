"""Interpolation weights of the fusion (paper §III-C, eqs. W1..W4 and their normalisation).

For a pixel ``p = (i, j)`` and a selected multi-view point ``q = (u, v)`` of Ω the
unnormalised weight is the product of

* ``W1 = exp(-‖p - q‖ / σ1)`` — proximity (pixels);
* ``W2 = 1 / ((|∂x s_q - ∂x s_p| + σ2) · (|∂y s_q - ∂y s_p| + σ2))`` — similar depth gradients;
* ``W3 = exp(-|s_p + ∂x s_p · (u - i) - s_q|) + σ3`` — q on the plane of p along x;
* ``W4 = exp(-|s_p + ∂y s_p · (v - j) - s_q|) + σ3`` — q on the plane of p along y;

with depths in metres and depth gradients in metres per pixel of the working grid, exactly
as the paper writes them. The weight set ``'w1'``, ``'w1w2'`` or ``'all'`` selects the
factors (the paper's Table III ablation).

Everything here works on torch tensors that broadcast: pixel quantities shaped ``(C, 1)``
and point quantities ``(1, Q)`` give a ``(C, Q)`` weight block, so the same code serves the
exact chunked sum, the fast mode and the tests, on CPU or CUDA.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

log = logging.getLogger(__name__)

WEIGHT_SETS = ('w1', 'w1w2', 'all')

#: Largest exponent magnitude fed to ``exp``: exp(-60) ≈ 9e-27 is still a normal float32
#: (denormals, below ~1e-38, make CPU arithmetic many times slower), and next to σ3 ≥ 1e-6
#: or any nearby point it is indistinguishable from zero in float32.
MAX_EXPONENT = 60.0


@dataclass(frozen=True)
class WeightParams:
    """σ1 (pixels), σ2 (metres per pixel), σ3 (dimensionless), the weight set, and the
    structure scale: the length (m) in which W2-W4 measure depths (1: the paper's metres)."""

    sigma1: float = 15.0
    sigma2: float = 0.1
    sigma3: float = 1e-3
    weights: str = 'all'
    structure_scale: float = 1.0

    def __post_init__(self) -> None:
        check_weight_params(self.sigma1, self.sigma2, self.sigma3, self.weights)
        check_structure_scale(self.structure_scale)

    @property
    def use_w2(self) -> bool:
        return self.weights in ('w1w2', 'all')

    @property
    def use_w34(self) -> bool:
        return self.weights == 'all'

    @property
    def max_weight(self) -> float:
        """Weight of a point that coincides with the pixel and shares its structure.

        The upper bound of one point's weight: ``W1 = 1``, ``W2 = 1/σ2²``, ``W3 = W4 = 1 + σ3``.
        The fast mode scales the structure factors by it.
        """
        w = 1.0
        if self.use_w2:
            w /= self.sigma2 * self.sigma2
        if self.use_w34:
            w *= (1.0 + self.sigma3) ** 2
        return w


def check_weight_params(sigma1: float, sigma2: float, sigma3: float, weights: str) -> None:
    """Raise a ``ValueError`` naming the parameter when a weight parameter is unusable."""
    if not (np.isfinite(sigma1) and sigma1 > 0):
        raise ValueError(f'sigma1 must be a positive number of pixels, got {sigma1}')
    if not (np.isfinite(sigma2) and sigma2 > 0):
        raise ValueError(f'sigma2 must be positive (it bounds W2 by 1/sigma2^2), got {sigma2}')
    if not (np.isfinite(sigma3) and sigma3 >= 0):
        raise ValueError(f'sigma3 must be >= 0, got {sigma3}')
    if weights not in WEIGHT_SETS:
        raise ValueError(f'weights must be one of {", ".join(WEIGHT_SETS)}, got {weights!r}')


def check_structure_scale(scale: float) -> None:
    """Raise a ``ValueError`` unless the structure scale is a positive length in metres."""
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f'structure_scale must be a positive length in metres, got {scale}')


def depth_gradients(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth gradients ``(∂x s, ∂y s)`` of ``s`` in metres per pixel (float32).

    Central differences inside, one-sided at the image border (``np.gradient``), which is
    what "the depth gradient at a pixel" means on the working grid. Where a neighbour is
    NaN the difference is NaN; those gradients are set to 0 (a flat surface) so a hole in
    ``s`` never poisons the weights of the pixels around it.
    """
    s = np.asarray(s, dtype=np.float32)
    if s.ndim != 2 or min(s.shape) < 2:
        raise ValueError(f'single-view depth must be an HxW image with H, W >= 2, got shape {s.shape}')
    gy, gx = np.gradient(s)
    gx = np.where(np.isfinite(gx), gx, 0.0).astype(np.float32)
    gy = np.where(np.isfinite(gy), gy, 0.0).astype(np.float32)
    return gx, gy


class Samples(NamedTuple):
    """Per-sample quantities the weights need; each tensor broadcasts against the others.

    ``x``/``y`` are pixel coordinates (column, row), ``s`` the single-view depth and
    ``gx``/``gy`` its gradients at those pixels.
    """

    x: torch.Tensor
    y: torch.Tensor
    s: torch.Tensor
    gx: torch.Tensor
    gy: torch.Tensor

    def column(self) -> Samples:
        """As ``(N, 1)`` (the pixel side of a weight block)."""
        return Samples(*(t.reshape(-1, 1) for t in self))

    def row(self) -> Samples:
        """As ``(1, N)`` (the point side of a weight block)."""
        return Samples(*(t.reshape(1, -1) for t in self))

    def take(self, index: torch.Tensor | slice) -> Samples:
        return Samples(*(t[index] for t in self))


def samples_at(
    flat_index: torch.Tensor, width: int, s: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor
) -> Samples:
    """:class:`Samples` of the pixels ``flat_index`` (row-major, 1-D) of flattened maps.

    Gathered by ``index_select``: the same values as advanced indexing, three to four times
    cheaper on a CPU (a whole image's pixels in the exact mode)."""
    x = (flat_index % width).to(s.dtype)
    y = torch.div(flat_index, width, rounding_mode='floor').to(s.dtype)
    return Samples(x, y, *(t.index_select(0, flat_index) for t in (s, gx, gy)))


def unnormalised_weights(
    p: Samples, q: Samples, params: WeightParams, lw: torch.Tensor | None = None
) -> torch.Tensor:
    """``W̃ = W1·W2·W3·W4`` (or the chosen subset) for every broadcast pair of ``p`` and ``q``.

    Reference formulation of the paper's factors; :mod:`.interpolation` evaluates it in
    chunks (optionally compiled into one fused loop). ``lw``: the points' log weights
    (broadcast like ``q``; None: 1), a factor ``exp(lw)`` of each point's weight.
    """
    dx = q.x - p.x
    dy = q.y - p.y
    w1 = proximity_weights(torch.sqrt(dx * dx + dy * dy), params, lw)
    if params.weights == 'w1':
        return w1
    return w1 * structure_weights(p, q, params, dx, dy)


def proximity_weights(
    distance: torch.Tensor, params: WeightParams, lw: torch.Tensor | None = None
) -> torch.Tensor:
    """W1 of pixel distances (times ``exp(lw)``, the points' own weights, when given)."""
    exponent = distance * (1.0 / params.sigma1)
    if lw is not None:
        exponent = exponent - lw
    return torch.exp(-exponent.clamp_max(MAX_EXPONENT))


def structure_weights(
    p: Samples, q: Samples, params: WeightParams, dx: torch.Tensor, dy: torch.Tensor
) -> torch.Tensor:
    """The factors of the weight that depend on ``s`` (W2, and W3·W4 for ``'all'``).

    ``dx``/``dy`` are ``q.x - p.x`` and ``q.y - p.y``. The fast mode's upsampling uses them
    alone to keep offsets from crossing depth edges. Without W2 (set ``'w1'``) it is 1.
    """
    if not params.use_w2:
        return torch.ones_like(dx * p.s)
    w = 1.0 / ((torch.abs(q.gx - p.gx) + params.sigma2) * (torch.abs(q.gy - p.gy) + params.sigma2))
    if params.use_w34:
        offset = p.s - q.s
        w3 = torch.exp(-torch.abs(offset + p.gx * dx).clamp_max(MAX_EXPONENT)) + params.sigma3
        w4 = torch.exp(-torch.abs(offset + p.gy * dy).clamp_max(MAX_EXPONENT)) + params.sigma3
        w = w * w3 * w4
    return w


def normalise_weights(w: torch.Tensor) -> torch.Tensor:
    """Per-pixel normalisation of a ``(P, Q)`` weight block over Ω (last axis), paper eq. (9).

    ``W = (W̃ - min W̃) / Σ (W̃ - min W̃)``: subtracting the minimum removes the far-field
    floor that every point of Ω would otherwise add. Guards: where every weight of a row
    is equal (always the case when ``|Ω| = 1``) the min-subtracted sum is 0, and the row
    falls back to plain normalisation ``W̃ / Σ W̃``; where even ``Σ W̃`` is 0 (every weight
    underflowed) it falls back to equal weights. Rows of an empty Ω stay empty.
    """
    if w.shape[-1] == 0:
        return w
    shifted = w - w.amin(dim=-1, keepdim=True)
    mass = shifted.sum(dim=-1, keepdim=True)
    plain = w.sum(dim=-1, keepdim=True)
    equal = torch.full_like(w, 1.0 / w.shape[-1])
    out = torch.where(mass > 0, shifted / mass.clamp_min(torch.finfo(w.dtype).tiny), w / plain)
    return torch.where(plain > 0, out, equal)
