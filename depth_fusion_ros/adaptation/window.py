"""The dense loss terms of a training step on a window of each keyframe: a quarter of the pixels.

A training step on the CPU (batch 3 at 320x240, one thread) costs about 0.27 s: the network's forward
and backward passes about half, the loss (the photometric error against two posed neighbours
per keyframe, with SSIM, and the smoothness) the other half; and a live node's training thread
gets a small share of a core. The network still sees whole keyframes (what it predicts
depends on the whole image: trained on parts of images or on smaller images, it learned
depths that did not carry over to the whole image, docs/adaptation.md, "Windows"), and the
sparse term still reads every multi-view point (a few hundred lookups); the photometric and
smoothness terms are computed on a window of the output, drawn anew for every keyframe of
every step by the step's seeded generator, so over the steps and replays they cover the
keyframe.

Everything depth-independent was computed once per keyframe on the whole output grid
(``prepared.py``); a window takes views of it: the keyframe's SSIM statistics, the unwarped
neighbours' error, the smoothness weights and the pixel rays (in the whole grid's pixel
coordinates, so the warp into the whole neighbour images is unchanged).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from .losses import KeyStats
from .prepared import GridTensors, PhotometricTensors


@dataclass(frozen=True)
class Window:
    """Rows ``top:top + height`` and columns ``left:left + width`` of the output grid."""

    top: int
    left: int
    height: int
    width: int

    def of(self, t: torch.Tensor, shrink_h: int = 0, shrink_w: int = 0) -> torch.Tensor:
        """The window of ``t``'s last two axes (``shrink_*``: a difference map one shorter)."""
        rows = slice(self.top, self.top + self.height - shrink_h)
        return t[..., rows, self.left : self.left + self.width - shrink_w]

    def photometric(self, p: PhotometricTensors | None) -> PhotometricTensors | None:
        """The keyframe side of ``p`` on the window; the neighbours (sampled wherever the warp
        lands) and the intrinsics stay whole."""
        if p is None:
            return None
        stats = KeyStats(*(self.of(t) for t in (p.stats.image, p.stats.mu, p.stats.mu_sq, p.stats.sigma)))
        rays = self.of(p.rays.view(3, *p.key.shape[-2:])).reshape(3, -1)  # the key is on the whole grid
        return dataclasses.replace(
            p,
            key=self.of(p.key),
            rays_key=(*p.rays_key, self.top, self.left),  # the rays are the window's own
            rays=rays,
            stats=stats,
            identity=self.of(p.identity),
        )

    def grid(self, g: GridTensors) -> GridTensors:
        """``g`` on the window."""
        return GridTensors(
            weight_x=self.of(g.weight_x, shrink_w=1),
            weight_y=self.of(g.weight_y, shrink_h=1),
            photometric=self.photometric(g.photometric),
        )


def draw_windows(
    count: int, full: tuple[int, int], fraction: float, rng: np.random.Generator
) -> list[Window]:
    """``count`` windows of ``fraction`` of the height and width of a ``full`` grid (at least
    one cell each), at random places.

    A place drawn uniformly among the windows that fit would cover a corner pixel only from
    one place of (H - h + 1)(W - w + 1): the offsets are drawn from half a window beyond each
    edge and clamped, so at half size a window touches each edge about a quarter of the time.
    """
    full_h, full_w = full
    h, w = max(1, round(full_h * fraction)), max(1, round(full_w * fraction))
    tops = np.clip(rng.integers(-(h // 2), full_h - h + h // 2 + 1, size=count), 0, full_h - h)
    lefts = np.clip(rng.integers(-(w // 2), full_w - w + w // 2 + 1, size=count), 0, full_w - w)
    return [Window(int(t), int(left), h, w) for t, left in zip(tops, lefts, strict=True)]


def cut(log_depth: torch.Tensor, windows: Sequence[Window]) -> torch.Tensor:
    """Each keyframe's window of ``log_depth`` (B, 1, H, W), stacked (all windows one size)."""
    return torch.cat([win.of(log_depth[b : b + 1]) for b, win in enumerate(windows)])
