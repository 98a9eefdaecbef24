"""An :class:`AdaptSample` turned into the tensors training needs, once per keyframe.

The network input is made by the predictor's own preprocessing (resize, normalisation,
channel order), so training sees exactly what inference sees. The photometric tensors (the
keyframe and its neighbours at the network's output grid, intrinsics of that grid,
keyframe-to-neighbour transforms) are built on first use, when the output grid is known.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from ..geometry import relative_pose
from .sample import AdaptSample


@dataclass
class PhotometricTensors:
    key: torch.Tensor  # (1, 3, h, w) in [0, 1]
    neighbours: torch.Tensor  # (N, 3, h, w) in [0, 1], gain-matched to the keyframe
    k: torch.Tensor  # (3, 3) intrinsics of the (h, w) grid
    t_ok: torch.Tensor  # (N, 4, 4)


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
        self._photo: dict[tuple[int, int], PhotometricTensors | None] = {}
        self._image: dict[tuple[int, int], torch.Tensor] = {}

    @property
    def n_train(self) -> int:
        return int(self.train_uv.shape[0])

    @property
    def n_holdout(self) -> int:
        return int(self.holdout_uv.shape[0])

    def image(self, height: int, width: int) -> torch.Tensor:
        """The keyframe in [0, 1] at (height, width) (for the smoothness edges)."""
        if (height, width) not in self._image:
            self._image[(height, width)] = _small(self.sample.rgb, height, width, self.device)
        return self._image[(height, width)]

    def photometric(self, height: int, width: int) -> PhotometricTensors | None:
        """Photometric tensors on the (height, width) grid, or None without poses."""
        if (height, width) not in self._photo:
            self._photo[(height, width)] = self._build_photometric(height, width)
        return self._photo[(height, width)]

    def _build_photometric(self, height: int, width: int) -> PhotometricTensors | None:
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
        return PhotometricTensors(key, neigh, k, torch.from_numpy(t_ok).to(self.device))
