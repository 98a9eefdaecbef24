"""Validated keyframe + neighbour views: the input both multi-view estimators share.

Checking inputs once here gives the user a message that names the bad image or pose,
instead of a shape error from deep inside torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..camera import PinholeCamera
from ..geometry import relative_pose, validate_pose


@dataclass
class Views:
    """Keyframe and neighbours as one grey stack on ``device`` plus relative poses ``T_ok``."""

    grays: torch.Tensor  # (1 + n, H, W) float32 in [0, 1]; index 0 is the keyframe
    T_ok: np.ndarray  # (n, 4, 4) keyframe camera -> neighbour camera
    camera: PinholeCamera
    device: torch.device

    @property
    def num_neighbours(self) -> int:
        return int(self.T_ok.shape[0])


def _as_gray(image: np.ndarray, what: str, camera: PinholeCamera) -> np.ndarray:
    image = np.asarray(image)
    if image.shape != (camera.height, camera.width):
        raise ValueError(
            f'{what}: expected a grey image of {camera.height}x{camera.width} (the camera), got {image.shape}'
        )
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    image = image.astype(np.float32)
    if not np.all(np.isfinite(image)):
        raise ValueError(f'{what}: grey image contains NaN or infinite values')
    return image


def prepare_views(
    key_gray: np.ndarray,
    key_pose: np.ndarray,
    neighbour_grays: Sequence[np.ndarray],
    neighbour_poses: Sequence[np.ndarray],
    camera: PinholeCamera,
    device: str | torch.device = 'cpu',
) -> Views:
    """Check images (grey float in [0, 1] or uint8, camera-sized) and poses (camera-to-world)."""
    if len(neighbour_grays) != len(neighbour_poses):
        raise ValueError(
            f'{len(neighbour_grays)} neighbour images but {len(neighbour_poses)} neighbour poses'
        )
    if len(neighbour_grays) == 0:
        raise ValueError('multi-view depth needs at least one neighbour frame, got none')
    T_wk = validate_pose(key_pose, 'keyframe pose')
    T_ok = np.stack(
        [relative_pose(T_wk, validate_pose(p, f'neighbour {i} pose')) for i, p in enumerate(neighbour_poses)]
    )
    grays = [_as_gray(key_gray, 'keyframe image', camera)]
    grays += [_as_gray(g, f'neighbour {i} image', camera) for i, g in enumerate(neighbour_grays)]
    dev = torch.device(device)
    return Views(torch.as_tensor(np.stack(grays), device=dev), T_ok, camera, dev)
