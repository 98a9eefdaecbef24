"""The Gaussian x uniform (Beta) update of a per-pixel inverse-depth estimate.

Vogiatzis & Hernandez, "Video-based, real-time multi-view stereo" (IVC 2011), as used by
SVO and REMODE. A measurement ``x`` of inverse depth with variance ``tau^2`` is, with
probability ``pi`` (the inlier ratio), a good measurement ``N(x | rho, tau^2)`` of the true
inverse depth ``rho``, and otherwise an outlier uniform over ``[rho_min, rho_max]``. The
posterior over ``(rho, pi)`` is approximated by ``N(rho | mu, sigma^2) Beta(pi | a, b)``
by moment matching. Why this model and not a plain Kalman filter: a wrong match (repetitive
texture, occlusion) would drag a Kalman mean away; here it mostly raises ``b`` (fewer
inliers), and a pixel whose inlier ratio ``a / (a + b)`` falls is dropped instead of
published wrong. A failed match (visible but nothing matched) is an outlier vote: ``b += 1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class BetaGaussian:
    """Per-pixel posterior: mean ``mu`` and variance ``var`` of inverse depth, Beta ``a``, ``b``."""

    mu: torch.Tensor
    var: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor

    @property
    def inlier_ratio(self) -> torch.Tensor:
        return self.a / (self.a + self.b)


def gaussian_uniform_update(
    prior: BetaGaussian, x: torch.Tensor, tau2: torch.Tensor, rho_range: tuple[float, float]
) -> BetaGaussian:
    """Posterior after one measurement per pixel (``x``, ``tau2`` shaped like the prior).

    Pure tensor arithmetic, so it runs for any number of pixels on any device.
    """
    mu, var, a, b = prior.mu, prior.var, prior.a, prior.b
    s2 = 1.0 / (1.0 / var + 1.0 / tau2)
    m = s2 * (mu / var + x / tau2)
    total = var + tau2
    # The repeated subexpressions (a + b, a + 1, ...) once each: the same operations in the
    # same order, so the same numbers, in about a third fewer passes.
    ab = a + b
    c1 = a / ab * torch.exp(-0.5 * (x - mu) ** 2 / total) / torch.sqrt(2.0 * math.pi * total)
    c2 = b / ab / (rho_range[1] - rho_range[0])
    norm = c1 + c2
    c1, c2 = c1 / norm, c2 / norm
    ab1 = ab + 1.0
    a1 = a + 1.0
    c1a1, c2a = c1 * a1, c2 * a
    f = c1a1 / ab1 + c2a / ab1
    ab12 = ab1 * (ab1 + 1.0)
    e = c1a1 * (a + 2.0) / ab12 + c2a * a1 / ab12
    mu_new = c1 * m + c2 * mu
    var_new = c1 * (s2 + m * m) + c2 * (var + mu * mu) - mu_new * mu_new
    a_new = (e - f) / (f - e / f)
    b_new = a_new * (1.0 - f) / f
    return BetaGaussian(mu_new, torch.clamp(var_new, min=1e-12), a_new, b_new)


def outlier_vote(prior: BetaGaussian, failed: torch.Tensor) -> BetaGaussian:
    """``b += 1`` where the pixel was visible but no match was found (``failed``, bool)."""
    return BetaGaussian(prior.mu, prior.var, prior.a, prior.b + failed.to(prior.b.dtype))
