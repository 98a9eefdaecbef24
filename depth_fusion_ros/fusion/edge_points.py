"""Points that sample only the single view's depth edges: a correction its edge explains is no evidence.

Why: in a room with little texture the silhouettes are the only texture, so the multi-view
points lie on them (76-83 % within 3 px of a depth edge on the stress case ``low_texture``,
against 12 % of the pixels) and say nothing about the surfaces between. There a network's
depth is blurred: it reads the foreground 5-8 % too far at the points, while over the image it
may read a few per cent too near, and a third of the points are halos (the foreground's depth
on the background's pixels, ``occlusion.py``). Both ask for a nearer depth than the image needs,
and the interpolation carries those corrections onto the walls between the silhouettes: seeds
152 and 301 of that case were fused 1.63x and 1.05x their single view through the node graph
(docs/fusion.md, "Points only on the single view's edges"). Where the points sample the image
evenly (TUM, 7-Scenes, every textured stress case), the same corrections at edges are right and
are needed.

How, per keyframe of a metric source (:func:`edge_explained`):

1. **the single view's depth edges**: pixels where its log depth changes by more than
   :data:`EDGE_STEP` between :data:`EDGE_SPAN` px on either side, across or down;
2. **the points' concentration there**: the share of the stage-1 points on those edges
   (``edge_share``) against the share of the valid pixels (``edge_ratio``). Only a keyframe
   whose points lie there at least ``min_ratio`` times as often as the pixels, and at least
   :data:`MIN_SHARE` of them, is changed: its points describe the silhouettes, not the surfaces;
3. **each point's correction, less what the edge explains**: a point whose depth the single
   view reaches within :data:`RADIUS_PX` (the blur of its edge and the width of a halo) agrees
   with it, and its correction is 0; beyond that range only the excess counts. In log depth,
   ``m <- s · exp(clip(0, log m - max, log m - min))``, ``min`` / ``max`` the single view's
   least and largest log depth within the radius. On a surface the range is narrow and the
   point keeps nearly all its correction.

The gate is measured, not derived (docs/fusion.md): the two failing streams' keyframes read a
ratio of 2.6-3.9 at 45-64 % of the points; textured streams 0.9-2.5 (TUM fr1_xyz 1.1-1.2,
7-Scenes 0.9-1.5). A low-texture stream the fusion helps because its network is far off
(seed 321, 0.40x its single view) reads 2.6-3.1 too, and loses part of that gain (0.53x):
the points alone cannot tell a network off between the silhouettes from one right there.
"""

from __future__ import annotations

import cv2
import numpy as np

#: A pixel is on the single view's depth edge where its log depth changes by more than this
#: between EDGE_SPAN px on either side, across or down (0.1: a 10 % step).
EDGE_STEP = 0.1
EDGE_SPAN = 3
#: The keyframe's points must be at least this share on the edges (with ``min_ratio``).
MIN_SHARE = 0.45
#: The range (px) within which a point's depth counts as the single view's own: the blur of a
#: network's edge (2-4 px at 320x240) and a halo's width (up to 3 px).
RADIUS_PX = 5


def check_edge_ratio(value: float) -> None:
    """``edge_ratio`` is 0 (off) or a concentration of at least 1."""
    if not (np.isfinite(value) and (value == 0 or value >= 1)):
        raise ValueError(f'edge_ratio must be 0 (off) or a number >= 1, got {value}')


def depth_edges(log_depth: np.ndarray) -> np.ndarray:
    """Pixels (HxW bool) where ``log_depth`` changes by more than :data:`EDGE_STEP` across
    2 x :data:`EDGE_SPAN` px, horizontally or vertically (NaN: no edge)."""
    k = EDGE_SPAN
    edges = np.zeros(log_depth.shape, dtype=bool)
    with np.errstate(invalid='ignore'):
        edges[:, k:-k] |= np.abs(log_depth[:, 2 * k :] - log_depth[:, : -2 * k]) > EDGE_STEP
        edges[k:-k, :] |= np.abs(log_depth[2 * k :, :] - log_depth[: -2 * k, :]) > EDGE_STEP
    return edges


def edge_concentration(log_depth: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """The share of ``points`` (HxW bool) on the single view's depth edges, and that share
    over the share of its valid pixels there."""
    edges = depth_edges(log_depth)
    n = int(np.count_nonzero(points))
    if n == 0:
        return 0.0, 0.0
    share = float(np.count_nonzero(edges & points)) / n
    pixels = float(np.count_nonzero(edges)) / max(int(np.count_nonzero(np.isfinite(log_depth))), 1)
    return share, share / max(pixels, 1e-3)


def local_range(log_depth: np.ndarray, radius: int = RADIUS_PX) -> tuple[np.ndarray, np.ndarray]:
    """The least and largest finite ``log_depth`` within ``radius`` px of each pixel (a square
    window; +inf / -inf where it holds none)."""
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    finite = np.isfinite(log_depth)
    low = cv2.erode(np.where(finite, log_depth, np.inf).astype(np.float32, copy=False), kernel)
    high = cv2.dilate(np.where(finite, log_depth, -np.inf).astype(np.float32, copy=False), kernel)
    return low, high


def edge_explained(
    single: np.ndarray, mv: np.ndarray, points: np.ndarray, min_ratio: float
) -> tuple[np.ndarray, dict[str, float]]:
    """``mv`` with the corrections of ``points`` (HxW bool, finite positive multi-view depths;
    a point whose single-view depth is not positive is left as it is) cut to what the single
    view's edges do not explain, where the keyframe's points concentrate on them (see the
    module's docstring); ``mv`` itself otherwise. Also the evidence: ``edge_share``,
    ``edge_ratio`` and ``edge_explained`` (the share of the points whose correction became 0;
    0 when the keyframe was left as it is). ``min_ratio`` 0: off, no evidence."""
    if min_ratio <= 0:
        return mv, {}
    with np.errstate(invalid='ignore', divide='ignore'):
        log_s = np.log(single).astype(np.float32, copy=False)
    share, ratio = edge_concentration(log_s, points)
    evidence = {'edge_share': share, 'edge_ratio': ratio, 'edge_explained': 0.0}
    if share < MIN_SHARE or ratio < min_ratio:
        return mv, evidence
    low, high = local_range(log_s)
    points = points & np.isfinite(log_s)  # a point on a non-positive single view has no log to cut
    log_m = np.log(mv[points])
    correction = np.clip(0.0, log_m - high[points], log_m - low[points])
    out = mv.copy()
    out[points] = (single[points] * np.exp(correction)).astype(mv.dtype)
    evidence['edge_explained'] = float(np.count_nonzero(correction == 0)) / max(len(correction), 1)
    return out, evidence
