"""The halo test of ``occlusion.py`` in torch, for a fusion that runs on a GPU.

Why a second implementation: the test is a few dozen array operations over every stage-1
point (20-30k a keyframe). On the CPU, NumPy and OpenCV do them in 6-11 ms and torch takes
three times as long (its sorts and gathers at this size); on a GPU's host the NumPy version
took 19.4 ms of a keyframe on an H200, this one 7.0 ms (docs/performance.md "GPU",
2026-12-04), because the arithmetic stays on the device.

It is ``occlusion.halo_points`` step for step, with the same constants, and gives the same
points: OpenCV 5's bilinear ``remap`` is the exact bilinear interpolation written out below,
its Gaussian blur and Sobel filters are the separable convolutions below with the same
reflected border, and NumPy's median is the mean of the two middle values
(test/test_fusion_halo.py compares the two on the CPU).
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from .occlusion import BEYOND_PX, BLUR_SIGMA, MIN_POINTS, NEAR_SHARE, SEARCH_PX, SIDE_PX

#: Sobel's 3-tap derivative and smoothing kernels (OpenCV's ksize=3).
_DERIVATIVE = (-1.0, 0.0, 1.0)
_SMOOTH = (1.0, 2.0, 1.0)


def halo_points_torch(
    gray: np.ndarray,
    base: np.ndarray,
    m: np.ndarray,
    points: np.ndarray,
    min_step: float,
    device: torch.device,
) -> np.ndarray:
    """``occlusion.halo_points`` on ``device``, after its checks (``gray``: the keyframe's grey
    image, ``occlusion.gray_image``, on the points' grid): the HxW bool mask of the halo's points."""
    gray = torch.as_tensor(gray, device=device)
    s = torch.as_tensor(base, dtype=torch.float32, device=device)
    md = torch.as_tensor(m, dtype=torch.float32, device=device)
    log_s = torch.log(torch.where(torch.isfinite(s) & (s > 0), s, torch.nan))
    usable = torch.as_tensor(points, device=device) & torch.isfinite(log_s) & torch.isfinite(md) & (md > 0)
    rows, cols = torch.nonzero(usable, as_tuple=True)
    if rows.numel() < MIN_POINTS:
        return np.zeros(points.shape, dtype=bool)
    log_m = torch.log(md[rows, cols])
    scale = _median(log_m - log_s[rows, cols])
    x, y = cols.to(torch.float32), rows.to(torch.float32)
    nx, ny, peak = _edge_offsets(gray, x, y, rows, cols)
    finite = torch.isfinite(log_s)
    filled = torch.where(finite, log_s, _median(log_s[finite]))
    near_side, far_side, ramp, grows = _single_view_sides(filled, x, y, nx, ny)
    step = far_side - near_side
    offset = torch.where(grows, -peak, peak)
    halo = (step - ramp > min_step) & (offset > 0)
    halo &= log_m - scale < near_side + NEAR_SHARE * step
    log_points = torch.full(points.shape, torch.nan, dtype=torch.float32, device=device)
    log_points[rows, cols] = log_m
    c = torch.nonzero(halo).flatten()
    if c.numel():
        far_log = far_side[c] + scale
        beyond = _beyond_agrees(log_points, y[c], x[c], nx[c], ny[c], grows[c], log_m[c], far_log)
        halo[c[beyond]] = False
    out = torch.zeros(points.shape, dtype=torch.bool, device=device)
    out[rows[halo], cols[halo]] = True
    return out.cpu().numpy()


def _median(values: torch.Tensor) -> torch.Tensor:
    """``np.median`` of a 1-D tensor: the mean of the two middle values (torch's median is the
    lower one)."""
    n = values.numel()
    low = torch.kthvalue(values, (n - 1) // 2 + 1).values
    high = torch.kthvalue(values, n // 2 + 1).values
    return (low + high) / 2


def bilinear(image: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``point_lookup.bilinear_at`` (OpenCV's ``remap``, bilinear, borders replicated) of an
    HxW float32 image at float32 pixel coordinates."""
    h, w = image.shape
    xf, yf = torch.floor(x), torch.floor(y)
    fx, fy = x - xf, y - yf
    x0, y0 = xf.to(torch.int64), yf.to(torch.int64)
    xa, xb = x0.clamp(0, w - 1), (x0 + 1).clamp(0, w - 1)
    top, bottom = y0.clamp(0, h - 1) * w, (y0 + 1).clamp(0, h - 1) * w
    flat = image.reshape(-1)
    upper = flat[top + xa] * (1 - fx) + flat[top + xb] * fx
    lower = flat[bottom + xa] * (1 - fx) + flat[bottom + xb] * fx
    return upper * (1 - fy) + lower * fy


@functools.lru_cache(maxsize=4)
def _kernel(kx: tuple[float, ...], ky: tuple[float, ...]) -> np.ndarray:
    return np.outer(np.asarray(ky, dtype=np.float32), np.asarray(kx, dtype=np.float32))


def _filter(image: torch.Tensor, kx: tuple[float, ...], ky: tuple[float, ...]) -> torch.Tensor:
    """``cv2.sepFilter2D`` with OpenCV's default border (reflected, edge pixel not repeated)."""
    k = torch.as_tensor(_kernel(kx, ky), device=image.device)[None, None]
    r = k.shape[-1] // 2
    return F.conv2d(F.pad(image[None, None], (r, r, r, r), mode='reflect'), k)[0, 0]


def _edge_offsets(
    gray: torch.Tensor, x: torch.Tensor, y: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``occlusion._edge_offsets``: unit gradient direction at each point and the sub-pixel
    offset of the gradient magnitude's peak along it."""
    # GaussianBlur's own size for a float image and sigma: cvRound(8 sigma + 1) | 1.
    size = round(8 * BLUR_SIGMA + 1) | 1
    gauss = tuple(float(v) for v in cv2.getGaussianKernel(size, BLUR_SIGMA, cv2.CV_32F).ravel())
    g = _filter(gray, gauss, gauss)
    gx, gy = _filter(g, _DERIVATIVE, _SMOOTH), _filter(g, _SMOOTH, _DERIVATIVE)
    magnitude = torch.sqrt(gx * gx + gy * gy)
    norm = torch.clamp(magnitude[rows, cols], min=1e-6)
    nx, ny = gx[rows, cols] / norm, gy[rows, cols] / norm
    steps = torch.arange(-SEARCH_PX, SEARCH_PX + 1, dtype=torch.float32, device=gray.device)
    samples = bilinear(magnitude, x[:, None] + steps * nx[:, None], y[:, None] + steps * ny[:, None])
    j = torch.clamp(torch.argmax(samples, dim=1), 1, 2 * SEARCH_PX - 1)[:, None]
    left, centre, right = (torch.gather(samples, 1, j + k)[:, 0] for k in (-1, 0, 1))
    curvature = left - 2.0 * centre + right
    peaked = curvature < -1e-9
    delta = torch.where(peaked, 0.5 * (left - right) / torch.where(peaked, curvature, -1.0), 0.0)
    return nx, ny, steps[j[:, 0]] + torch.clamp(delta, -1.0, 1.0)


def _single_view_sides(
    log_s: torch.Tensor, x: torch.Tensor, y: torch.Tensor, nx: torch.Tensor, ny: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``occlusion._single_view_sides``: near and far sides, the ramp, the far side's direction."""
    reach = torch.tensor([SIDE_PX, -SIDE_PX, 2 * SIDE_PX, -2 * SIDE_PX], dtype=torch.float32, device=x.device)
    sides = bilinear(log_s, x[:, None] + reach * nx[:, None], y[:, None] + reach * ny[:, None])
    plus, minus, plus2, minus2 = sides.T
    ramp = torch.sign(plus - minus) * ((plus2 - plus) + (minus - minus2))
    return torch.minimum(plus, minus), torch.maximum(plus, minus), ramp, plus > minus


def _beyond_agrees(
    log_points: torch.Tensor,
    y: torch.Tensor,
    x: torch.Tensor,
    nx: torch.Tensor,
    ny: torch.Tensor,
    grows: torch.Tensor,
    log_m: torch.Tensor,
    far_log: torch.Tensor,
) -> torch.Tensor:
    """``occlusion._beyond_agrees``: whether the points beyond each candidate speak for it."""
    h, w = log_points.shape
    dev = x.device
    sign = torch.where(grows, 1.0, -1.0)
    ts = torch.arange(BEYOND_PX[0], BEYOND_PX[1] + 1, dtype=torch.float32, device=dev)
    lateral = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float32, device=dev)
    along = sign[:, None, None] * ts[None, :, None]
    xs = x[:, None, None] + along * nx[:, None, None] - lateral[None, None, :] * ny[:, None, None]
    ys = y[:, None, None] + along * ny[:, None, None] + lateral[None, None, :] * nx[:, None, None]
    xi = torch.clamp(torch.round(xs).to(torch.int64), 0, w - 1)
    yi = torch.clamp(torch.round(ys).to(torch.int64), 0, h - 1)
    samples = torch.sort(log_points[yi, xi].reshape(len(x), -1), dim=1).values  # NaN (no point) last
    count = torch.isfinite(samples).sum(dim=1)
    idx = torch.arange(len(x), device=dev)
    low, high = torch.clamp(count - 1, min=0) // 2, torch.clamp(count // 2, max=samples.shape[1] - 1)
    beyond = 0.5 * (samples[idx, low] + samples[idx, high])
    return (count >= 2) & (torch.abs(beyond - log_m) < torch.abs(beyond - far_log))
