"""Training-time augmentation of (RGB, depth) pairs that keeps the geometry consistent.

* **Zoom crop**: cut a random window of ``1/s`` of the image (``s`` in ``[1, max_zoom]``)
  and resize it back to the input size. That is the image a camera with focal length
  ``s·f`` would see; a pinhole camera with focal ``s·f`` sees an object at depth ``z``
  exactly as large as a camera with focal ``f`` sees it at ``z/s``, so the target depth is
  divided by ``s`` (Eigen et al. 2014). The network always sees the training camera's
  focal length, i.e. the intrinsics stay right. Depth is resampled with nearest neighbour
  so holes (NaN) and depth edges never blend.
* **Horizontal flip** (the mirrored camera has the same focal length).
* **Colour jitter**: brightness, contrast and saturation factors in ``[1 − j, 1 + j]``.

Everything draws from one ``torch.Generator`` so a training step is reproducible from
``(seed, step)`` alone, which is what makes resume exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

#: ITU-R 601 luma weights (as ``rgb_to_gray``) for the saturation jitter.
LUMA = (0.299, 0.587, 0.114)


@dataclass
class AugmentConfig:
    max_zoom: float = 1.25
    flip: bool = True
    jitter: float = 0.2

    def validate(self) -> None:
        if self.max_zoom < 1:
            raise ValueError(f'max_zoom must be >= 1, got {self.max_zoom}')
        if not 0 <= self.jitter < 1:
            raise ValueError(f'jitter must be in [0, 1), got {self.jitter}')


def _uniform(gen: torch.Generator, n: int, lo: float, hi: float) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(n, generator=gen)


def zoom_crop(
    rgb: torch.Tensor, depth: torch.Tensor, zoom: torch.Tensor, fx: torch.Tensor, fy: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per image ``i``: window of size ``(W, H) / zoom[i]`` at fractional position
    ``(fx[i], fy[i])`` in [0, 1], resized back to ``(H, W)``; depth divided by ``zoom[i]``.

    ``rgb`` (B, 3, H, W) float, ``depth`` (B, 1, H, W) float with NaN holes.
    """
    _, _, h, w = rgb.shape
    out_rgb, out_depth = [], []
    for i in range(rgb.shape[0]):
        s = float(zoom[i])
        cw, ch = max(2, round(w / s)), max(2, round(h / s))
        x0 = round(float(fx[i]) * (w - cw))
        y0 = round(float(fy[i]) * (h - ch))
        crop_rgb = rgb[i : i + 1, :, y0 : y0 + ch, x0 : x0 + cw]
        crop_depth = depth[i : i + 1, :, y0 : y0 + ch, x0 : x0 + cw]
        if (ch, cw) != (h, w):
            crop_rgb = F.interpolate(crop_rgb, size=(h, w), mode='bilinear', align_corners=False)
            crop_depth = F.interpolate(crop_depth, size=(h, w), mode='nearest')
        out_rgb.append(crop_rgb)
        out_depth.append(crop_depth * (ch / h + cw / w) / 2)  # the exact zoom after rounding
    return torch.cat(out_rgb), torch.cat(out_depth)


def colour_jitter(rgb: torch.Tensor, gen: torch.Generator, amount: float) -> torch.Tensor:
    """Random brightness, contrast and saturation per image; ``rgb`` in [0, 1], (B, 3, H, W)."""
    if amount <= 0:
        return rgb
    b = rgb.shape[0]
    bright = _uniform(gen, b, 1 - amount, 1 + amount).view(b, 1, 1, 1).to(rgb)
    contrast = _uniform(gen, b, 1 - amount, 1 + amount).view(b, 1, 1, 1).to(rgb)
    sat = _uniform(gen, b, 1 - amount, 1 + amount).view(b, 1, 1, 1).to(rgb)
    rgb = rgb * bright
    luma = (rgb * torch.tensor(LUMA, device=rgb.device).view(1, 3, 1, 1)).sum(dim=1, keepdim=True)
    rgb = (rgb - luma.mean(dim=(2, 3), keepdim=True)) * contrast + luma.mean(dim=(2, 3), keepdim=True)
    luma = (rgb * torch.tensor(LUMA, device=rgb.device).view(1, 3, 1, 1)).sum(dim=1, keepdim=True)
    rgb = (rgb - luma) * sat + luma
    return rgb.clamp(0, 1)


def augment_batch(
    rgb: torch.Tensor, depth: torch.Tensor, cfg: AugmentConfig, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Augment a batch: ``rgb`` (B, 3, H, W) in [0, 1], ``depth`` (B, 1, H, W) metres/NaN."""
    b = rgb.shape[0]
    zoom = _uniform(gen, b, 1.0, cfg.max_zoom)
    pos_x, pos_y = torch.rand(b, generator=gen), torch.rand(b, generator=gen)
    if cfg.max_zoom > 1:
        rgb, depth = zoom_crop(rgb, depth, zoom, pos_x, pos_y)
    if cfg.flip:
        flip = (torch.rand(b, generator=gen) < 0.5).to(rgb.device)
        rgb = torch.where(flip.view(b, 1, 1, 1), rgb.flip(-1), rgb)
        depth = torch.where(flip.view(b, 1, 1, 1), depth.flip(-1), depth)
    rgb = colour_jitter(rgb, gen, cfg.jitter)
    return rgb, depth
