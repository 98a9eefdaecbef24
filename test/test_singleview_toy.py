"""Toy RGB-D data for the single-view tests (imported by test_singleview_*.py; no tests here).

Scenes: a tilted background plane at 2-4 m and a few fronto-parallel rectangles at 0.8-2 m.
Colour follows depth (nearer = brighter) plus per-object tint and texture noise, so a tiny
network learns it in a few dozen steps; depth is exact, with a few NaN holes like a Kinect.
"""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.sequence import Frame, Sequence
from depth_fusion_ros.singleview.training_data import DepthSamples

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def toy_frame(width: int, height: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8 HxWx3, depth float32 HxW with a few NaN) of one toy scene."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    depth = rng.uniform(2.0, 3.0) + rng.uniform(-1, 1) * u / width + rng.uniform(0, 1) * v / height
    tint = np.ones((height, width, 3), np.float32)
    for _ in range(rng.integers(1, 4)):
        w, h = rng.integers(width // 6, width // 2), rng.integers(height // 6, height // 2)
        x0, y0 = rng.integers(0, width - w), rng.integers(0, height - h)
        depth[y0 : y0 + h, x0 : x0 + w] = rng.uniform(0.8, 2.0)
        tint[y0 : y0 + h, x0 : x0 + w] = rng.uniform(0.6, 1.0, 3)
    brightness = np.clip(1.25 - depth / 4.0, 0.05, 1.0)
    rgb = brightness[..., None] * tint * 255 + rng.normal(0, 4, (height, width, 3))
    depth = depth.astype(np.float32)
    holes = rng.random((height, width)) < 0.01
    depth[holes] = np.nan
    return np.clip(rgb, 0, 255).astype(np.uint8), depth


def toy_samples(n: int, width: int, height: int, seed: int = 0) -> DepthSamples:
    rng = np.random.default_rng(seed)
    frames = [toy_frame(width, height, rng) for _ in range(n)]
    return DepthSamples(
        rgb=np.stack([f[0] for f in frames]),
        depth=np.stack([f[1] for f in frames]).astype(np.float16),
        sequence_index=np.zeros(n, np.int32),
        sequences=[f'toy{seed}'],
        focal_px=[width * 0.8],
    )


def toy_sequence(n: int = 4, width: int = 64, height: int = 48, seed: int = 0) -> Sequence:
    """A ``Sequence`` of toy frames (ground truth at the working resolution)."""
    rng = np.random.default_rng(seed)
    camera = PinholeCamera(width, height, 0.8 * width, 0.8 * width, width / 2 - 0.5, height / 2 - 0.5)
    frames = []
    for i in range(n):
        rgb, depth = toy_frame(width, height, rng)
        frames.append(Frame(index=i, stamp=i / 30, rgb=rgb, pose=np.eye(4), depth=depth))
    return Sequence(name=f'toy{seed}', camera=camera, frames=frames, gt_camera=camera)
