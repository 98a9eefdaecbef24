"""Tiny exact renderer of textured planes, for the multi-view tests and benchmark.

The multi-view search only needs images with exact depth and poses; a few textured planes
rendered by inverse warping (ray-plane intersection, bilinear texture lookup) give exactly
that in milliseconds, without the full synthetic-sequence renderer of ``data/synthetic/``.
A plane may be texture-less (constant grey) to check that such areas get no estimate.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import PinholeCamera


@dataclass(frozen=True)
class Plane:
    """The plane ``normal . X = offset`` (world frame), textured with ``texture_scale`` m per texel.

    ``textured=False`` paints it a constant grey.
    """

    normal: tuple[float, float, float]
    offset: float
    textured: bool = True
    texture_scale: float = 0.004
    seed: int = 0
    #: Optional world-space box ``(x_min, x_max, y_min, y_max)`` outside which the plane is absent.
    bounds: tuple[float, float, float, float] | None = None


@functools.lru_cache(maxsize=16)
def random_texture(size: int, seed: int) -> np.ndarray:
    """Periodic multi-scale smoothed noise in [0.1, 0.9] (strong at every scale, like natural texture).

    Blurred in the Fourier domain so the texture tiles seamlessly when the lookup wraps.
    """
    rng = np.random.default_rng(seed)
    freq = np.fft.fftfreq(size)
    f2 = freq[:, None] ** 2 + freq[None, :] ** 2
    tex = np.zeros((size, size), dtype=np.float64)
    for sigma, weight in ((0.8, 0.5), (2.0, 0.8), (6.0, 1.0), (16.0, 1.0)):
        spectrum = np.fft.fft2(rng.standard_normal((size, size)))
        blurred = np.real(np.fft.ifft2(spectrum * np.exp(-2.0 * (np.pi * sigma) ** 2 * f2)))
        tex += weight * blurred / (blurred.std() + 1e-12)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    out = (0.1 + 0.8 * tex).astype(np.float32)
    out.setflags(write=False)  # cached: shared between calls
    return out


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, normal)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def render_planes(
    planes: list[Plane], camera: PinholeCamera, pose: np.ndarray, texture_size: int = 512
) -> tuple[np.ndarray, np.ndarray]:
    """Grey image (float32, [0, 1]) and exact z-depth (m, NaN where no plane) seen from ``pose``.

    The nearest plane in front of the camera wins (z-buffer); textures wrap around.
    """
    u, v = camera.pixel_grid()
    rays_c = np.stack(((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)), axis=-1)
    R, t = pose[:3, :3], pose[:3, 3]
    rays_w = rays_c @ R.T
    depth = np.full(u.shape, np.inf)
    gray = np.zeros(u.shape, dtype=np.float32)
    for plane in planes:
        n = np.asarray(plane.normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        denom = rays_w @ n
        with np.errstate(divide='ignore', invalid='ignore'):
            z = (plane.offset - n @ t) / denom  # z-depth because rays have unit z
        hit = np.isfinite(z) & (z > 1e-6) & (z < depth)
        with np.errstate(invalid='ignore'):
            X = t + rays_w * np.where(hit, z, 0.0)[..., None]
        if plane.bounds is not None:
            x0, x1, y0, y1 = plane.bounds
            hit &= (X[..., 0] >= x0) & (X[..., 0] <= x1) & (X[..., 1] >= y0) & (X[..., 1] <= y1)
        if not np.any(hit):
            continue
        depth[hit] = z[hit]
        if not plane.textured:
            gray[hit] = 0.5
            continue
        e1, e2 = _plane_basis(n)
        tex = random_texture(texture_size, plane.seed)
        map_x = ((X @ e1) / plane.texture_scale).astype(np.float32)
        map_y = ((X @ e2) / plane.texture_scale).astype(np.float32)
        map_x, map_y = np.mod(map_x, texture_size), np.mod(map_y, texture_size)
        sample = cv2.remap(tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        gray[hit] = sample[hit]
    depth[~np.isfinite(depth)] = np.nan
    return gray, depth.astype(np.float32)


def look_at_pose(
    position: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, -1.0, 0.0)
) -> np.ndarray:
    """Camera-to-world pose at ``position`` looking at ``target``.

    Optical frame: x right, y down, z forward; ``up`` is the world direction shown upwards.
    """
    z = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, dtype=np.float64), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack((x, y, z), axis=1)
    T[:3, 3] = position
    return T


def default_scene(texel: float = 0.006) -> list[Plane]:
    """A textured back wall at 3 m, a textured floor 0.6 m below the camera, and a slanted board at ~1.5 m.

    ``texel`` (m) is the texture resolution: keep it near the pixel footprint at the far wall
    (``3 m / fx``) or coarser, since the renderer does not filter textures (aliasing would make
    the appearance depend on the viewpoint).
    """
    return [
        Plane((0.0, 0.0, 1.0), 3.0, seed=1, texture_scale=texel),
        Plane((0.0, 1.0, 0.0), 0.6, seed=2, texture_scale=texel),
        Plane((0.3, 0.0, 1.0), 1.5, seed=3, texture_scale=0.75 * texel, bounds=(-0.6, 0.4, -0.5, 0.3)),
    ]
