"""Feature matches tracked with an affine window: the second image's position of each match
found by warping the first image's window (Lucas-Kanade with an affine warp, a gain and an offset).

Why: ORB fires wherever its corner response peaks in each image on its own, a pixel or a
pyramid level's pixel apart (on a rendered robot's stream, 0.7 px from where the first position's
surface point went, at the median). Under forward motion a window grows and shears between the
two images, so a tracker that only shifts it (:mod:`.match_refinement`) is pulled by the part of
the window that changed most. An affine warp follows the window as a plane's image moves: on the
same stream the tracked positions lie 0.1 px from the truth at the median. The mount check fits a
turn of a degree or two from these positions, and what every pair's matches share in error it
reads as a turn (docs/multi_view.md, "Matches tracked with an affine window").

The warp is found by inverse-compositional Gauss-Newton (Baker and Matthews, 2004): the first
image's window, its gradients and their normal matrix are computed once per match; each step
samples the second image under the current warp, matches its gain and offset to the window, and
composes the inverse of the solved step. All matches of a pair run at once (one ``cv2.remap`` per
step). The first position stays as detected: the window is centred on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

#: Half the window's side (px): 15 x 15 pixels, weighted by a Gaussian of :data:`SIGMA`.
RADIUS = 7
SIGMA = RADIUS / 1.5
#: Gauss-Newton steps allowed, and the step (px) under which a match has converged.
ITERATIONS = 20
TOLERANCE_PX = 0.01
#: A tracked position is kept within this of the matched keypoint (px), with the warp's area
#: scale between these (a plane's image seldom doubles between two samples)...
MOVE_TOLERANCE_PX = 3.0
AREA_RANGE = (0.5, 2.0)
#: ...and the window's contrast in the second image at least this share of the first's.
MIN_GAIN = 0.2

_OFFSETS = np.arange(-RADIUS, RADIUS + 1, dtype=np.float64)
_GX, _GY = (a.ravel() for a in np.meshgrid(_OFFSETS, _OFFSETS))
_WEIGHTS = np.exp(-(_GX**2 + _GY**2) / (2.0 * SIGMA**2))
_WEIGHTS /= _WEIGHTS.sum()
#: The window's offsets as rows (3, N) of ``(1, x, y)``: a warp's positions are one product.
_OFFSET_ROWS = np.stack([np.ones_like(_GX), _GX, _GY])


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (float64) of a float32 image at positions ``x``, ``y`` (M, N)."""
    mx, my = x.astype(np.float32), y.astype(np.float32)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)


def _gradient(image: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """Central difference of a float32 image along x (``dx=1``) or y (``dy=1``)."""
    return cv2.Sobel(image, cv2.CV_32F, dx, dy, ksize=1) * 0.5


def _warped(t: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The window's pixel positions (M, N) in the second image under warps ``A x + t``."""
    rows = np.concatenate([t[:, :, None], A], axis=2)  # (M, 2, 3): each coordinate's (t, a_x, a_y)
    xy = rows @ _OFFSET_ROWS
    return xy[:, 0], xy[:, 1]


def _gain_matched(
    window: np.ndarray, template: np.ndarray, variance: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The second image's windows (M, N) with their weighted mean taken off, and the gain that
    matches them to the zero-mean templates (M,)."""
    centred = window - (window @ _WEIGHTS)[:, None]
    return centred, (centred * template) @ _WEIGHTS / variance


@dataclass(frozen=True)
class AffineTemplates:
    """The first image's windows at its points, ready to track into any second image: what
    depends on the first image only (windows, gradients, the normal matrices' inverses), made
    once. The pose refinement tracks one keyframe's corners into every frame that follows it."""

    points: np.ndarray  # (M, 2) positions in the first image
    template: np.ndarray  # (M, N) zero-mean windows
    variance: np.ndarray  # (M,)
    descent: np.ndarray  # (M, 6, N) steepest descent images through the inverse normal matrices


def affine_templates(first: np.ndarray, p1: np.ndarray) -> AffineTemplates:
    """The windows of a grey uint8 image at ``p1`` (M, 2), ready for :func:`track_templates`."""
    if len(p1) == 0:
        n = _GX.size
        return AffineTemplates(np.zeros((0, 2)), np.zeros((0, n)), np.zeros(0), np.zeros((0, 6, n)))
    a = first.astype(np.float32)
    x, y = p1[:, :1] + _GX, p1[:, 1:] + _GY
    template = _sample(a, x, y)
    template -= (template @ _WEIGHTS)[:, None]
    variance = (template * template) @ _WEIGHTS + 1e-9
    tx, ty = _sample(_gradient(a, 1, 0), x, y), _sample(_gradient(a, 0, 1), x, y)
    # The steepest descent images as rows (M, 6, N), so that the normal matrices and each step's
    # right-hand side are batched matrix products (einsum over these was half the tracking's time).
    jacobian = np.stack([tx, ty, tx * _GX, tx * _GY, ty * _GX, ty * _GY], axis=1)
    weighted = jacobian * _WEIGHTS
    normal = weighted @ np.transpose(jacobian, (0, 2, 1))
    damping = 1e-6 * np.trace(normal, axis1=1, axis2=2)[:, None, None] + 1e-12
    descent = np.linalg.inv(normal + damping * np.eye(6)) @ weighted  # (M, 6, N): a step is one product
    return AffineTemplates(p1, template, variance, descent)


def track_affine(
    first: np.ndarray, second: np.ndarray, p1: np.ndarray, p2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Matches ``p1 -> p2`` (M, 2) of two grey uint8 images with ``p2`` tracked from ``p1``'s
    window under an affine warp; the matches whose tracking converged within
    :data:`MOVE_TOLERANCE_PX` of ``p2`` (``p1`` as detected, the tracked ``p2``)."""
    return track_templates(affine_templates(first, p1), second, p2)[:2]


class AffineTracks(NamedTuple):
    """What :func:`track_templates` found: the kept points in the first image and in the
    second, which of the tracked points were kept (a mask), and the kept points' warps."""

    first: np.ndarray  # (N, 2)
    second: np.ndarray  # (N, 2)
    kept: np.ndarray  # (M,) bool
    warps: np.ndarray  # (N, 2, 2): the affine part, first window -> second


def track_templates(
    templates: AffineTemplates,
    second: np.ndarray,
    p2: np.ndarray,
    subset: np.ndarray | None = None,
    iterations: int = ITERATIONS,
    warps: np.ndarray | None = None,
) -> AffineTracks:
    """:func:`track_affine` from windows made once: ``subset`` (indices into ``templates``) are
    the points tracked, to ``p2`` (len(subset), 2); all of them when ``None``. ``iterations``:
    the Gauss-Newton steps allowed (a match still moving after them is dropped). ``warps``
    (len(subset), 2, 2): where each window's affine part starts (the identity when ``None``);
    the pose refinement starts a frame's windows at the previous frame's warps, which the
    windows have nearly reached, so that fewer steps converge. Also returns which of the
    tracked points were kept (a mask over ``p2``) and their warps: the pose refinement goes on
    from the kept ones in the next frame."""
    if subset is not None:
        t = templates
        templates = AffineTemplates(
            t.points[subset], t.template[subset], t.variance[subset], t.descent[subset]
        )
    p1, template, variance, descent = (
        templates.points,
        templates.template,
        templates.variance,
        templates.descent,
    )
    if len(p1) == 0:
        return AffineTracks(p1, p2, np.zeros(0, dtype=bool), np.zeros((0, 2, 2)))
    b = second.astype(np.float32)
    t = np.asarray(p2, dtype=np.float64).copy()
    A = np.tile(np.eye(2), (len(p1), 1, 1)) if warps is None else np.array(warps, dtype=np.float64)
    if A.shape != (len(p1), 2, 2):
        raise ValueError(f'warps must be ({len(p1)}, 2, 2), one per tracked point, got {A.shape}')
    # Each window's gain as last sampled: a converged window's last step moved it less than
    # TOLERANCE_PX, so no final pass samples every window again to read it.
    gain = np.zeros(len(p1))
    # The rows each step reads (``rows``: which match each is) and which of them still move. A
    # row that converged stays, unmoved, until a quarter have: copying the rows out at every
    # step cost as much as the steps.
    rows, live = np.arange(len(p1)), np.ones(len(p1), dtype=bool)
    tm, var = template, variance
    for _ in range(iterations):
        centred, g = _gain_matched(_sample(b, *_warped(t[rows], A[rows])), tm, var)
        gain[rows] = g
        residual = centred / np.where(np.abs(g) > 1e-3, g, 1e-3)[:, None] - tm
        step = (descent @ residual[:, :, None])[live, :, 0]
        i = rows[live]
        # The warp composed with the step's inverse.
        A[i] = A[i] @ np.linalg.inv(np.eye(2) + step[:, 2:].reshape(-1, 2, 2))
        t[i] -= (A[i] @ step[:, :2, None])[:, :, 0]
        live[live] = np.linalg.norm(step[:, :2], axis=1) > TOLERANCE_PX
        if not live.any():
            break
        if live.sum() < 0.75 * len(rows):
            rows, descent, tm, var = rows[live], descent[live], tm[live], var[live]
            live = np.ones(len(rows), dtype=bool)
    moving = np.zeros(len(p1), dtype=bool)
    moving[rows[live]] = True
    area = np.linalg.det(A)
    keep = (
        ~moving
        & np.isfinite(t).all(axis=1)
        & (np.linalg.norm(t - p2, axis=1) < MOVE_TOLERANCE_PX)
        & (area > AREA_RANGE[0])
        & (area < AREA_RANGE[1])
        & (gain > MIN_GAIN)
    )
    return AffineTracks(p1[keep], t[keep], keep, A[keep])
