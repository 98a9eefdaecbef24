"""Synthetic depth scenes with exact ground truth for the fusion's tests and benchmark.

A slanted back plane with boxes in front of it: planar patches separated by depth edges,
the structure the weights W2..W4 are designed for. No rendering and no camera model are
needed — the fusion sees only depth images on a pixel grid. One scene is rendered
(:func:`rendered_halo_keyframe`): the halo test needs a keyframe image whose edges are the
depth's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FusionScene:
    """``depth``: true depth (m); ``single``: a distorted single-view depth; ``multi``:
    semi-dense multi-view depth (NaN = none), exact at ``good`` and wrong at ``outliers``."""

    depth: np.ndarray
    single: np.ndarray
    multi: np.ndarray
    good: np.ndarray
    outliers: np.ndarray


def planes_and_boxes(width: int = 80, height: int = 60, boxes: int = 2, seed: int = 0) -> np.ndarray:
    """True depth (float32, m): a slanted plane at ~2-3 m and ``boxes`` fronto-slanted boxes."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    depth = 2.0 + 0.8 * xx / width + 0.4 * yy / height
    for _ in range(boxes):
        w = rng.uniform(0.2, 0.35) * width
        h = rng.uniform(0.25, 0.4) * height
        x0 = rng.uniform(0.05, 0.95) * width - w / 2
        y0 = rng.uniform(0.05, 0.95) * height - h / 2
        inside = (xx >= x0) & (xx < x0 + w) & (yy >= y0) & (yy < y0 + h)
        base = rng.uniform(1.0, 1.6)
        depth[inside] = base + rng.uniform(-0.3, 0.3) * (xx[inside] - x0) / width
    return depth.astype(np.float32)


def make_scene(
    width: int = 80,
    height: int = 60,
    n_points: int = 60,
    n_outliers: int = 0,
    scale: float = 0.8,
    offset: float = 0.3,
    seed: int = 0,
) -> FusionScene:
    """A scene whose single-view depth is ``scale·depth + offset`` (globally wrong, locally
    right) and whose multi-view depth has ``n_points`` exact points, ``n_outliers`` of them
    then pushed 0.5-2 m off (a wrong match)."""
    rng = np.random.default_rng(seed)
    depth = planes_and_boxes(width, height, seed=seed)
    single = (scale * depth + offset).astype(np.float32)
    index = rng.choice(depth.size, size=n_points, replace=False)
    multi = np.full(depth.shape, np.nan, dtype=np.float32)
    multi.ravel()[index] = depth.ravel()[index]
    outliers = np.zeros(depth.shape, dtype=bool)
    outliers.ravel()[index[:n_outliers]] = True
    multi[outliers] += rng.uniform(0.5, 2.0, size=n_outliers).astype(np.float32)
    good = np.isfinite(multi) & ~outliers
    return FusionScene(depth, single, multi, good, outliers)


def rendered_halo_keyframe(
    width: int = 160, height: int = 120, point_share: float = 0.6
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rgb, single, multi, points)``: a rendered room keyframe, a noisy single view (5 % far,
    blurred), and multi-view points on ``point_share`` of the pixels, half of them fattened
    across the depth edges (the nearer depth 2 px away): halos, ramps and regions off at once,
    for the halo test (``occlusion.py``) and its torch twin."""
    from scipy.ndimage import gaussian_filter

    from ..data.synthetic import SynthConfig, render_sequence

    frame = render_sequence(SynthConfig(width=width, height=height, frames=2, seed=4), max_frames=1).frames[0]
    depth = frame.depth.astype(np.float32)
    rng = np.random.default_rng(9)
    single = np.exp(gaussian_filter(np.log(depth * 1.05), 1.5) + rng.normal(0.0, 0.02, depth.shape))
    near = np.minimum.reduce([np.roll(depth, s, axis=a) for s in (-2, 0, 2) for a in (0, 1)])
    multi = np.where(rng.random(depth.shape) < 0.5, near, depth) * rng.normal(1.0, 0.02, depth.shape)
    points = rng.random(depth.shape) < point_share
    return frame.rgb, single.astype(np.float32), multi.astype(np.float32), points


#: The posts of :func:`posts_keyframe` and the wall behind them (m).
POST_DEPTH, WALL_DEPTH = 2.2, 3.0


def posts_keyframe(
    width: int, height: int, posts: list[tuple[int, int]], rows: tuple[int, int], blur: float
) -> FusionScene:
    """A low-texture keyframe whose multi-view points lie on silhouettes only (the failure of
    ``edge_points.py``): posts (x ranges ``posts``, y range ``rows``, exclusive ends) at
    :data:`POST_DEPTH` before a wall at :data:`WALL_DEPTH`; the post's depth 3 px inside each
    side edge (``good``) and 2 px outside it (``outliers``: the halo), 4 px short of the post's
    ends; a network's single view, 3 % too near over the image and blurred by ``blur`` px (in log
    depth)."""
    from scipy.ndimage import gaussian_filter

    yy, xx = np.mgrid[0:height, 0:width]
    top, bottom = rows
    depth = np.full((height, width), WALL_DEPTH, dtype=np.float32)
    good = np.zeros((height, width), dtype=bool)
    halo = np.zeros((height, width), dtype=bool)
    inside = (yy >= top + 4) & (yy < bottom - 4)
    for x0, x1 in posts:
        depth[(xx >= x0) & (xx < x1) & (yy >= top) & (yy < bottom)] = POST_DEPTH
        good |= inside & (((xx >= x0) & (xx < x0 + 3)) | ((xx >= x1 - 3) & (xx < x1)))
        halo |= inside & (((xx >= x0 - 2) & (xx < x0)) | ((xx >= x1) & (xx < x1 + 2)))
    single = np.exp(gaussian_filter(np.log(depth * 0.97), blur)).astype(np.float32)
    multi = np.where(good | halo, POST_DEPTH, np.nan).astype(np.float32)
    return FusionScene(depth, single, multi, good, halo)
