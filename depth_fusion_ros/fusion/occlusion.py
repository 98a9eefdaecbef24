"""Multi-view points in a silhouette's halo: the foreground's depth on the background's pixels.

A patch matcher (the ZNCC of the sweep and of the filter, ``multiview/descriptors.py``) gives a
pixel just outside a foreground object the *foreground's* depth. Its patch holds the object's
silhouette, often the only texture there, and the silhouette moves with the object between the
views, so the patch matches best at the object's depth ("foreground fattening", a classic of
stereo matching). Every silhouette then carries a halo of points one or two pixels wide, too
near by the whole depth step. Measured on the stress case ``low_texture`` (seed 31, the shipped
network, causal neighbours): 25-35 % of the multi-view points are more than 10 % off, 66-97 % of
those are too near, and 90-96 % of those carry a depth the ground truth has within 2 px. They sit
in tight lines along the silhouettes, so the guard's local test (each point against its
neighbours, ``guard.py``) sees them agree with each other; their corrections, weighed as
similar to the background (their single-view depth is the background's), spread into the
walls around. There the fused depth was worse than the single view (1.04x over the stream).

The keyframe image and the single-view depth tell the halo apart; the multi-view depth alone
cannot (both sides of the silhouette carry the foreground's depth). Per point ``p``, along the
direction ``n`` of the image gradient at ``p``:

1. **the intensity edge**: the sub-pixel peak of the gradient magnitude within
   ``±SEARCH_PX`` of ``p`` (parabolic fit around the largest sample);
2. **an occluding edge there**: the single-view log depth at ``p ± SIDE_PX · n`` differs by more
   than ``min_step``, beyond what a ramp explains (the same spans further out: a slanted floor
   or wall changes its depth steadily and does not count);
3. **p on the far side**: the single-view step says which side of the edge is farther, and ``p``
   lies on that side of the peak;
4. **a foreground depth**: the point's multi-view depth is nearer than halfway (in log depth)
   between the two sides' single-view depths, scaled to the points by their median ratio;
5. **nothing beyond says otherwise**: the multi-view points ``BEYOND_PX`` further on the far
   side (two or more of them) are not nearer the point's depth than the far side's. Where they
   are, the single view's step is its own error (a region of the prediction off, its border on
   an image edge), not an occlusion, and the point is right.

The five together drop 2-14 % of the points of a stress case's stream (docs/fusion.md
"Silhouette halos"; most on ``low_texture``). Where the single-view depth has no step at an
edge, or the point lies on its near side, the point is kept: the test removes no point the
single view cannot place. On a CPU the five steps run point by point in C (``native_halo.py``,
``halo_test.c``: the same halos bit for bit, 2-3x faster); the numpy code below is the
reference and runs where the kernel cannot.
The single view's step must sit at the image's edge for the side to be right; a single view
from the image (a network) has its edges there, one from a misregistered depth camera may not
(docs/fusion.md: TUM's ground-truth edges lie -1.7 to +2.2 px off the image's).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..data.sequence import rgb_to_gray
from ..point_lookup import bilinear_at
from ..torch_device import resolve_device
from .native_halo import HaloShape, native_halo

#: Half-length (px) of the search for the intensity edge along the gradient direction.
SEARCH_PX = 3
#: Distance (px) on each side of a point at which the single-view depth is read: past the
#: blur of a network's depth edge (2-4 px at 320x240) and of the halo itself.
SIDE_PX = 6.0
#: Grey-image blur (Gaussian sigma, px) before the gradient: a little more than the
#: descriptors' 0.5, so that a sharp step's gradient peaks on a parabola.
BLUR_SIGMA = 0.7
#: A halo point's depth is nearer than this share of the step from the near side (log depth).
NEAR_SHARE = 0.5
#: The span (px, from, to) beyond a point on the far side whose points may speak for it.
BEYOND_PX = (3, 8)
#: Fewer points than this: nothing to scale the single view with, nothing tested.
MIN_POINTS = 20


def check_min_step(min_step: float) -> None:
    if not (np.isfinite(min_step) and min_step >= 0):
        raise ValueError(f'halo_min_step must be a finite number >= 0 (0: off), got {min_step}')


def gray_image(image: np.ndarray) -> np.ndarray:
    """Float32 grey image from an HxW grey or HxWx3 RGB image (``data.sequence.rgb_to_gray``,
    the matcher's own grey; any scale: only gradients count)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 3:
        return rgb_to_gray(a)
    if a.ndim != 2:
        raise ValueError(f'keyframe image must be HxW or HxWx3, got shape {a.shape}')
    return a.astype(np.float32)


def halo_points(
    image: np.ndarray,
    base: np.ndarray,
    m: np.ndarray,
    points: np.ndarray,
    min_step: float = 0.1,
    device: str = 'cpu',
) -> np.ndarray:
    """The points of ``points`` (HxW bool) that sit in a silhouette's halo (see the module doc).

    ``image``: the keyframe (grey or RGB, the working grid); ``base``: the single-view depth the
    fusion starts from (metres, any global scale); ``m``: the multi-view depth. Returns an HxW
    bool mask, a subset of ``points``; empty when ``min_step`` is 0 or the points are too few.
    ``device``: the fusion's; off the CPU the same test runs in torch (``occlusion_gpu.py``).
    """
    out = np.zeros(points.shape, dtype=bool)
    if min_step <= 0:
        return out
    gray = gray_image(image)
    if gray.shape != points.shape:
        raise ValueError(f'keyframe image {gray.shape} and depth {points.shape} differ in size')
    dev = resolve_device(device)
    if dev.type != 'cpu':
        from .occlusion_gpu import halo_points_torch  # it imports this module's constants

        return halo_points_torch(gray, base, m, points, min_step, dev)
    with np.errstate(invalid='ignore', divide='ignore'):
        log_s = np.log(np.where(np.isfinite(base) & (base > 0), base, np.nan)).astype(np.float32)
        finite = np.isfinite(log_s)
        usable = points & finite & np.isfinite(m) & (m > 0)
    rows, cols = np.nonzero(usable)
    if len(rows) < MIN_POINTS:
        return out
    log_m = np.log(m[rows, cols].astype(np.float32))
    scale = float(np.median(log_m - log_s[rows, cols]))
    gx, gy, magnitude = _gradients(gray)
    # The holes filled with the median (a network's depth has none: no median over the image)
    filled = log_s if finite.all() else np.where(finite, log_s, np.float32(np.median(log_s[finite])))
    log_points = np.full(points.shape, np.nan, dtype=np.float32)
    log_points[rows, cols] = log_m
    shape = HaloShape(SEARCH_PX, SIDE_PX, NEAR_SHARE, BEYOND_PX)
    native = native_halo(magnitude, gx, gy, filled, log_points, rows, cols, log_m, scale, min_step, shape)
    if native is not None:  # the same five steps point by point, bit for bit
        out[rows[native], cols[native]] = True
        return out
    # Float32 coordinates: every sample position below is computed in float32 (half the work).
    x, y = cols.astype(np.float32), rows.astype(np.float32)
    nx, ny, peak = _edge_offsets(gx, gy, magnitude, x, y, rows, cols)
    near_side, far_side, ramp, grows = _single_view_sides(filled, x, y, nx, ny)
    step = far_side - near_side  # >= 0 by construction: the far side's log depth minus the near's
    # Step 3: the far side is +n where the depth grows along n; p is at -peak from the edge.
    offset = np.where(grows, -peak, peak)
    halo = (step - ramp > min_step) & (offset > 0)
    halo &= log_m - scale < near_side + NEAR_SHARE * step
    # Step 5 on the candidates only (a fifth of the points or fewer: it is the costly one).
    c = np.flatnonzero(halo)
    if c.size:
        far_log = far_side[c] + scale
        beyond = _beyond_agrees(log_points, y[c], x[c], nx[c], ny[c], grows[c], log_m[c], far_log)
        halo[c[beyond]] = False
    out[rows[halo], cols[halo]] = True
    return out


def _beyond_agrees(
    log_points: np.ndarray,
    y: np.ndarray,
    x: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    grows: np.ndarray,
    log_m: np.ndarray,
    far_log: np.ndarray,
) -> np.ndarray:
    """Whether the multi-view points beyond each point (``BEYOND_PX`` further on the far
    side, and 1 px to either side of that line; two or more of them) are nearer the point's
    log depth than the single view's far side (``far_log``, scaled to the points): then the
    single view's step is its own error (a region off), not an occlusion."""
    h, w = log_points.shape
    sign = np.where(grows, 1.0, -1.0).astype(np.float32)
    ts = np.arange(BEYOND_PX[0], BEYOND_PX[1] + 1, dtype=np.float32)
    lateral = np.array([-1.0, 0.0, 1.0], dtype=np.float32)
    along = sign[:, None, None] * ts[None, :, None]
    xs = x[:, None, None] + along * nx[:, None, None] - lateral[None, None, :] * ny[:, None, None]
    ys = y[:, None, None] + along * ny[:, None, None] + lateral[None, None, :] * nx[:, None, None]
    xi = np.clip(np.rint(xs).astype(np.intp), 0, w - 1)
    yi = np.clip(np.rint(ys).astype(np.intp), 0, h - 1)
    samples = np.sort(log_points[yi, xi].reshape(len(x), -1), axis=1)  # NaN (no point) last
    count = np.isfinite(samples).sum(axis=1)
    # The median of each row's finite samples (np.nanmedian is ten times slower here).
    idx = np.arange(len(x))
    low, high = np.maximum(count - 1, 0) // 2, count // 2
    beyond = 0.5 * (samples[idx, low] + samples[idx, np.minimum(high, samples.shape[1] - 1)])
    return (count >= 2) & (np.abs(beyond - log_m) < np.abs(beyond - far_log))


def _gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blurred grey image's Sobel derivatives and gradient magnitude (float32)."""
    g = cv2.GaussianBlur(gray, (0, 0), BLUR_SIGMA)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    return gx, gy, cv2.magnitude(gx, gy)


def _edge_offsets(
    gx: np.ndarray,
    gy: np.ndarray,
    magnitude: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """Unit gradient direction at each point (``x``, ``y``: float32 coordinates; ``rows``,
    ``cols``: the same as indices) and the sub-pixel offset (along it) of the gradient
    magnitude's peak within ``±SEARCH_PX``."""
    norm = np.maximum(magnitude[rows, cols], np.float32(1e-6))
    nx, ny = gx[rows, cols] / norm, gy[rows, cols] / norm
    steps = np.arange(-SEARCH_PX, SEARCH_PX + 1, dtype=np.float32)
    samples = bilinear_at(magnitude, x[:, None] + steps * nx[:, None], y[:, None] + steps * ny[:, None])
    # The largest sample away from the ends, refined by a parabola through it and its neighbours.
    j = np.clip(np.argmax(samples, axis=1), 1, 2 * SEARCH_PX - 1)[:, None]
    left, centre, right = (np.take_along_axis(samples, j + k, axis=1)[:, 0] for k in (-1, 0, 1))
    j = j[:, 0]
    curvature = left - 2.0 * centre + right
    peaked = curvature < -1e-9
    delta = np.where(peaked, 0.5 * (left - right) / np.where(peaked, curvature, -1.0), 0.0)
    return nx, ny, steps[j] + np.clip(delta, -1.0, 1.0)


def _single_view_sides(
    log_s: np.ndarray, x: np.ndarray, y: np.ndarray, nx: np.ndarray, ny: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The near and far sides' single-view log depth at ``±SIDE_PX``, the change a ramp
    would make over the same span (from the spans beyond, ``SIDE_PX`` to ``2 SIDE_PX``), and
    whether the far side is along ``n`` (``+SIDE_PX``)."""
    reach = np.array([SIDE_PX, -SIDE_PX, 2 * SIDE_PX, -2 * SIDE_PX], dtype=np.float32)
    sides = bilinear_at(log_s, x[:, None] + reach * nx[:, None], y[:, None] + reach * ny[:, None])
    plus, minus, plus2, minus2 = sides.T
    sign = np.sign(plus - minus)
    ramp = sign * ((plus2 - plus) + (minus - minus2))
    return np.minimum(plus, minus), np.maximum(plus, minus), ramp, plus > minus
