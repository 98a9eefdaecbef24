"""An :class:`AdaptSample` turned into the tensors training needs, once per keyframe.

The network input is made by the predictor's own preprocessing (resize, normalisation,
channel order), so training sees exactly what inference sees. Everything a training step
needs that does not depend on the predicted depth is computed here once, on the adapter's
device, and reused by every step and every replay of the keyframe (a replayed keyframe costs
no preparation at all):

* at construction: the network input, the normalised sampling grids and log depths of the
  training and held-out points;
* on first use of an output grid (its size is known after the first forward pass): the
  keyframe and its gain-matched neighbours on that grid, the grid's intrinsics and pixel
  rays, the keyframe-to-neighbour transforms, the keyframe's SSIM statistics, the
  photometric error of the *unwarped* neighbours (the auto-mask's reference) and the
  edge-aware smoothness weights.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from ..geometry import relative_pose
from .losses import KeyStats, edge_weights, key_stats, photo_error_to_key, point_grid
from .sample import AdaptSample
from .warp import pixel_rays


@dataclass
class PhotometricTensors:
    key: torch.Tensor  # (1, 3, h, w) in [0, 1]
    neighbours: torch.Tensor  # (N, 3, h, w) in [0, 1], gain-matched to the keyframe
    k: torch.Tensor  # (3, 3) intrinsics of the (h, w) grid
    t_ok: torch.Tensor  # (N, 4, 4)
    #: What ``rays`` and ``k`` are made of, on the host, so a batch can tell without a device
    #: sync whether its keyframes share them: ``(fx, fy, cx, cy)`` of ``k``, and for a window
    #: of the grid (``window.py``) its ``(top, left)`` too, since its rays are its own.
    rays_key: tuple[float, ...]
    #: (3, h*w) rays ``K^-1 [u, v, 1]`` of the grid.
    rays: torch.Tensor
    #: SSIM statistics of the keyframe (constant: the keyframe is not warped).
    stats: KeyStats
    #: (N, 1, h, w) photometric error of each *unwarped* neighbour (for auto-masking).
    identity: torch.Tensor


@dataclass
class GridTensors:
    """What the loss needs on one output grid besides the depth."""

    #: Edge-aware smoothness weights ``exp(-|dI/dx|)`` (1, 1, h, w-1) and ``exp(-|dI/dy|)``
    #: (1, 1, h-1, w) of the keyframe on the grid.
    weight_x: torch.Tensor
    weight_y: torch.Tensor
    photometric: PhotometricTensors | None


def _small(rgb: np.ndarray, height: int, width: int, device: torch.device) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(2, 0, 1)[None].float() / 255.0
    if t.shape[-2:] != (height, width):
        t = F.interpolate(t, size=(height, width), mode='area')
    return t


class PreparedSample:
    """Tensors of one keyframe on ``device`` (built once, reused by every replay)."""

    def __init__(
        self,
        sample: AdaptSample,
        preprocess: Callable[[list[np.ndarray]], torch.Tensor],
        device: torch.device,
    ):
        self.sample = sample
        self.key = sample.key
        self.device = device
        self.x = preprocess([sample.rgb])
        self.height, self.width = sample.rgb.shape[:2]
        self.train_uv = torch.from_numpy(sample.train_uv).to(device)
        self.train_log = torch.from_numpy(np.log(sample.train_depth)).to(device)
        self.holdout_uv = torch.from_numpy(sample.holdout_uv).to(device)
        self.holdout_log = torch.from_numpy(np.log(sample.holdout_depth)).to(device)
        #: (N, 2) grid_sample coordinates of the points (as ``losses.sample_map`` makes them).
        self.train_grid = point_grid(self.train_uv, self.width, self.height)
        #: The starting network's log depth of this keyframe (the anchor's target), made on first use.
        self.anchor_log: torch.Tensor | None = None
        self.holdout_grid = point_grid(self.holdout_uv, self.width, self.height)
        #: The guard's (n_holdout,) held-out point errors of this keyframe, by weights token
        #: (see ``Adapter``).
        self.guard_errors: dict[int, torch.Tensor] = {}
        self._grid: dict[tuple[int, int, float], GridTensors] = {}
        self._image: dict[tuple[int, int], torch.Tensor] = {}

    @property
    def n_train(self) -> int:
        return int(self.train_uv.shape[0])

    @property
    def n_holdout(self) -> int:
        return int(self.holdout_uv.shape[0])

    @property
    def n_neighbours(self) -> int:
        return len(self.sample.neighbours) if self.sample.has_photometric else 0

    def image(self, height: int, width: int) -> torch.Tensor:
        """The keyframe in [0, 1] at (height, width) (for the smoothness edges)."""
        if (height, width) not in self._image:
            self._image[(height, width)] = _small(self.sample.rgb, height, width, self.device)
        return self._image[(height, width)]

    def grid(self, height: int, width: int, ssim_alpha: float = 0.85) -> GridTensors:
        """The depth-independent loss tensors on the (height, width) output grid, for the SSIM
        share ``ssim_alpha`` of the photometric error (cached)."""
        key = (int(height), int(width), float(ssim_alpha))
        if key not in self._grid:
            wx, wy = edge_weights(self.image(height, width))
            self._grid[key] = GridTensors(wx, wy, self._build_photometric(height, width, ssim_alpha))
        return self._grid[key]

    def photometric(self, height: int, width: int, ssim_alpha: float = 0.85) -> PhotometricTensors | None:
        """Photometric tensors on the (height, width) grid, or None without poses."""
        return self.grid(height, width, ssim_alpha).photometric

    def _build_photometric(self, height: int, width: int, ssim_alpha: float) -> PhotometricTensors | None:
        s = self.sample
        if not s.has_photometric:
            return None
        key = self.image(height, width)
        neigh = torch.cat([_small(n.rgb, height, width, self.device) for n in s.neighbours])
        # One gain per neighbour: auto-exposure changes the brightness between frames.
        gain = key.mean() / neigh.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-3)
        neigh = (neigh * gain).clamp(0, 1)
        cam = s.camera.scaled(width, height)
        k = torch.tensor(
            [[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=torch.float32, device=self.device
        )
        t_ok = np.stack([relative_pose(s.pose, n.pose) for n in s.neighbours]).astype(np.float32)
        stats = key_stats(key)
        return PhotometricTensors(
            key=key,
            neighbours=neigh,
            k=k,
            t_ok=torch.from_numpy(t_ok).to(self.device),
            rays_key=(float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)),
            rays=pixel_rays(torch.linalg.inv(k), height, width),
            stats=stats,
            identity=photo_error_to_key(neigh, stats, ssim_alpha),
        )
