"""Training samples (RGB + metric depth at the network's input size) from posed sequences.

Sequences come from TUM-layout folders through ``data.tum.load_tum_sequence``, which already
undistorts and resizes the colour images and reads the ground-truth depth images. Here each
frame becomes one sample at the network's input size: colour resized (area), depth resized
with nearest neighbour so holes stay holes. Depth is stored as float16 (1 mm at 2 m, half the
memory: 20 sequences x 100 frames take ~0.8 GB).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..data.sequence import Sequence, resize_depth

log = logging.getLogger(__name__)


@dataclass
class DepthSamples:
    """Aligned RGB/depth pairs of one or more sequences at one size."""

    rgb: np.ndarray  # (N, H, W, 3) uint8
    depth: np.ndarray  # (N, H, W) float16, metres, NaN = unknown
    #: Per sample: which sequence it comes from (index into ``sequences``).
    sequence_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    sequences: list[str] = field(default_factory=list)
    #: Per sequence: focal length (px) at the sample size, recorded in the model's metadata.
    focal_px: list[float] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return (int(self.rgb.shape[2]), int(self.rgb.shape[1]))

    def subset(self, indices: np.ndarray) -> DepthSamples:
        return DepthSamples(
            self.rgb[indices],
            self.depth[indices],
            self.sequence_index[indices],
            self.sequences,
            self.focal_px,
        )

    @staticmethod
    def concat(parts: Seq[DepthSamples]) -> DepthSamples:
        parts = [p for p in parts if len(p)]
        if not parts:
            raise ValueError('no training samples: every sequence was empty')
        sizes = {p.size for p in parts}
        if len(sizes) > 1:
            raise ValueError(f'samples of different sizes cannot be pooled: {sorted(sizes)}')
        offsets = np.cumsum([0] + [len(p.sequences) for p in parts])
        return DepthSamples(
            np.concatenate([p.rgb for p in parts]),
            np.concatenate([p.depth for p in parts]),
            np.concatenate([p.sequence_index + o for p, o in zip(parts, offsets, strict=False)]),
            [s for p in parts for s in p.sequences],
            [f for p in parts for f in p.focal_px],
        )


def samples_from_sequence(seq: Sequence, width: int, height: int, every: int = 1) -> DepthSamples:
    """Every ``every``-th frame of ``seq`` with ground truth, at ``width`` x ``height``."""
    rgbs, depths = [], []
    for frame in seq.frames[:: max(1, every)]:
        if frame.depth is None:
            continue
        rgb = frame.rgb
        if rgb.shape[:2] != (height, width):
            shrink = rgb.shape[1] > width
            rgb = cv2.resize(
                rgb, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
            )
        depth = resize_depth(frame.depth.astype(np.float32), width, height)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
        rgbs.append(rgb)
        depths.append(depth.astype(np.float16))
    if not rgbs:
        log.warning('%s: no frame has ground-truth depth, skipped', seq.name)
        return DepthSamples(
            np.zeros((0, height, width, 3), np.uint8), np.zeros((0, height, width), np.float16)
        )
    focal = seq.camera.scaled(width, height).fx
    return DepthSamples(
        np.stack(rgbs), np.stack(depths), np.zeros(len(rgbs), np.int32), [seq.name], [float(focal)]
    )


def load_folder_samples(
    path: str | Path, width: int, height: int, max_frames: int | None = None, every: int = 1
) -> DepthSamples:
    """Samples of one TUM-layout folder (loaded at ``width`` x ``height``)."""
    from ..data.tum import load_tum_sequence

    seq = load_tum_sequence(path, width=width, height=height, max_frames=max_frames)
    samples = samples_from_sequence(seq, width, height, every)
    samples.sequences = [str(path)] if len(samples) else []
    log.info('%s: %d training samples', path, len(samples))
    return samples


def split_validation(
    per_sequence: Seq[DepthSamples], fraction: float, gap: int = 5
) -> tuple[DepthSamples, DepthSamples]:
    """Hold out whole sequences (the last ``ceil(fraction · n)``) when there are several, so
    validation images are never near-duplicates of training ones; with a single sequence,
    hold out its last ``fraction`` of frames after dropping ``gap`` frames at the boundary."""
    if not 0 < fraction < 1:
        raise ValueError(f'validation fraction must be in (0, 1), got {fraction}')
    parts = [p for p in per_sequence if len(p)]
    if not parts:
        raise ValueError('no training samples to split')
    if len(parts) >= 2:
        n_val = max(1, math.ceil(fraction * len(parts)))
        n_val = min(n_val, len(parts) - 1)
        return DepthSamples.concat(parts[:-n_val]), DepthSamples.concat(parts[-n_val:])
    only = parts[0]
    n = len(only)
    n_val = max(1, round(fraction * n))
    n_train = n - n_val - gap
    if n_train < 1:
        raise ValueError(f'sequence {only.sequences} has only {n} frames: too few to split off validation')
    return only.subset(np.arange(n_train)), only.subset(np.arange(n - n_val, n))
