"""Numpy ray casting of a synthetic scene: exact z-depth, surface labels and shaded colour.

Every pixel's ray is ``X = o + t * d`` with the camera-frame direction
``d_c = ((u - cx) / fx, (v - cy) / fy, 1)`` (pixel centres per ``camera.py``), so the ray
parameter ``t`` at the hit *is* the z-depth: no conversion from range, no rounding. A lens
with radial distortion (``lens_k1``) only bends those slopes (``radial_lens.undistort_radial``);
``t`` stays the z-depth.

Rays are intersected with all boxes by the slab method, vectorised over pixels; each box
is only tested against the screen rectangle its projected corners cover, which keeps a
frame at 640x480 around a tenth of a second. Vectors are kept as three separate component
arrays (x, y, z) because numpy reductions along a length-3 axis are slow.

Shading is Lambertian (point light + ambient, no specular), so a surface point has the
same colour from every view (brightness constancy) and multi-view photometric matching is
exact up to sensor noise and resampling.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ...camera import PinholeCamera
from ...radial_lens import undistort_radial
from .scene import Scene

#: Hits closer than this along the ray (m) are ignored (the camera is never that close).
NEAR = 1e-3
#: Rotated-grid supersampling offsets (pixels) used on silhouette pixels.
RGSS_OFFSETS = np.array([[-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]])
#: Overall exposure: radiance 1.0 of a white surface maps to this grey level.
EXPOSURE = 235.0

Vec = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass
class RenderedFrame:
    """One rendered view: ``rgb`` uint8, ``depth`` float32 z-depth (m), ``surface`` int32
    surface index (``object * 6 + face``), ``textured`` bool (strongly textured material)."""

    rgb: np.ndarray
    depth: np.ndarray
    surface: np.ndarray
    textured: np.ndarray


def _slopes(
    camera: PinholeCamera, u: np.ndarray, v: np.ndarray, lens_k1: float
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray slopes (float32) of pixel positions ``u``, ``v``."""
    a, b = undistort_radial((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, lens_k1)
    return a.astype(np.float32), b.astype(np.float32)


@lru_cache(maxsize=8)
def _camera_rays(camera: PinholeCamera, lens_k1: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray slopes ``(x/z, y/z)`` of every pixel centre, (H, W) float32 each."""
    a, b = _slopes(camera, *camera.pixel_grid(), lens_k1)
    a.flags.writeable = False
    b.flags.writeable = False
    return a, b


def _rotate_rays(R: np.ndarray, a: np.ndarray, b: np.ndarray) -> Vec:
    """``R @ (a, b, 1)`` per pixel, as three component arrays."""
    R = R.astype(np.float32)
    return tuple(R[k, 0] * a + R[k, 1] * b + R[k, 2] for k in range(3))  # type: ignore[return-value]


def _slab_axis(o: float, d: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ray parameters through the slab ``|x| <= half`` along one axis."""
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = np.float32(1.0) / d
        t_a = np.float32(-half - o) * inv
        t_b = np.float32(half - o) * inv
    return np.fmin(t_a, t_b), np.fmax(t_a, t_b)


def _argmax3(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elementwise ``(max, argmax)`` of three arrays (ties go to the lower axis)."""
    best = np.maximum(np.maximum(x, y), z)
    axis = np.where(x == best, 0, np.where(y == best, 1, 2)).astype(np.int32)
    return best, axis


def _face_code(d_local: Vec, axis: np.ndarray) -> np.ndarray:
    """Face code ``2 * axis + (normal along +axis)``: the hit face faces the ray, so its
    normal is positive where the ray's component along that axis is negative."""
    d_axis = np.where(axis == 0, d_local[0], np.where(axis == 1, d_local[1], d_local[2]))
    return (2 * axis + (d_axis < 0)).astype(np.int32)


def _to_local(scene: Scene, obj: int, origin: np.ndarray, d: Vec) -> tuple[np.ndarray, Vec]:
    """Ray origin and directions in the frame of object ``obj`` (boxes only yaw about z)."""
    R = scene.rotations[obj]
    origin_local = R.T @ (origin - scene.centres[obj])
    if np.array_equal(R, np.eye(3)):
        return origin_local, d
    c, s = np.float32(R[0, 0]), np.float32(R[1, 0])
    return origin_local, (c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2])


def _room_exit(scene: Scene, origin: np.ndarray, d: Vec) -> tuple[np.ndarray, np.ndarray]:
    """Where rays from inside the room leave it: ``(t, surface)`` on the room's inner faces."""
    o, d_local = _to_local(scene, 0, origin, d)
    exits = [_slab_axis(o[k], d_local[k], scene.halves[0, k])[1] for k in range(3)]
    neg_t, axis = _argmax3(-exits[0], -exits[1], -exits[2])
    return -neg_t, _face_code(d_local, axis)


def _hit_box(scene: Scene, obj: int, origin: np.ndarray, d: Vec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry of rays into solid box ``obj``: ``(hit mask, t, surface index)``."""
    o, d_local = _to_local(scene, obj, origin, d)
    slabs = [_slab_axis(o[k], d_local[k], scene.halves[obj, k]) for k in range(3)]
    t_near, axis = _argmax3(slabs[0][0], slabs[1][0], slabs[2][0])
    t_far = np.minimum(np.minimum(slabs[0][1], slabs[1][1]), slabs[2][1])
    hit = (t_near <= t_far) & (t_near > NEAR)
    return hit, t_near, obj * 6 + _face_code(d_local, axis)


def cast_rays(scene: Scene, origin: np.ndarray, d: Vec) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit ``(t, surface)`` of rays from ``origin`` with world directions ``d``
    (three component arrays of any common shape); ``t`` is in units of ``|d|``."""
    t, surface = _room_exit(scene, origin, d)
    for obj in range(1, scene.n_objects):
        hit, t_obj, s_obj = _hit_box(scene, obj, origin, d)
        closer = hit & (t_obj < t)
        t = np.where(closer, t_obj, t)
        surface = np.where(closer, s_obj, surface)
    return t, surface


def _screen_rect(
    scene: Scene, obj: int, camera: PinholeCamera, T_wc: np.ndarray
) -> tuple[slice, slice] | None:
    """Pixel rectangle covering box ``obj`` (None if it is behind the camera or off screen)."""
    pts = (scene.corners()[obj] - T_wc[:3, 3]) @ T_wc[:3, :3]
    z = pts[:, 2]
    if np.all(z <= NEAR):
        return None
    if np.any(z <= NEAR):  # straddles the camera plane: the projection is unbounded
        return slice(0, camera.height), slice(0, camera.width)
    u = camera.fx * pts[:, 0] / z + camera.cx
    v = camera.fy * pts[:, 1] / z + camera.cy
    u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, camera.width)
    v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return slice(v0, v1), slice(u0, u1)


def cast_camera(
    scene: Scene, camera: PinholeCamera, T_wc: np.ndarray, lens_k1: float = 0.0
) -> tuple[np.ndarray, np.ndarray, Vec]:
    """Z-depth (H, W) float32, surface (H, W) int32 and world ray directions (3 x (H, W))
    of every pixel centre of a camera at pose ``T_wc`` (its lens distortion ``lens_k1``)."""
    origin = T_wc[:3, 3]
    d = _rotate_rays(T_wc[:3, :3], *_camera_rays(camera, lens_k1))
    t, surface = _room_exit(scene, origin, d)
    everywhere = (slice(0, camera.height), slice(0, camera.width))
    for obj in range(1, scene.n_objects):
        # A distorted lens bends a box's outline off its corners' pinhole rectangle: each box
        # is then tested over the whole image (slower, never wrong).
        rect = everywhere if lens_k1 else _screen_rect(scene, obj, camera, T_wc)
        if rect is None:
            continue
        hit, t_obj, s_obj = _hit_box(scene, obj, origin, (d[0][rect], d[1][rect], d[2][rect]))
        closer = hit & (t_obj < t[rect])
        t[rect] = np.where(closer, t_obj, t[rect])
        surface[rect] = np.where(closer, s_obj, surface[rect])
    return t, surface, d


def shade(
    scene: Scene, origin: np.ndarray, d: Vec, t: np.ndarray, surface: np.ndarray, focal: float
) -> np.ndarray:
    """Radiance (M, 3) float32 in grey levels of the surface points hit by M rays.

    Texture lookups use the surface's own UV frame (world-attached), with a mip level from
    the pixel footprint on the surface (distance / focal, stretched by obliquity), so far or
    grazing surfaces are prefiltered instead of aliased.
    """
    obj, face = np.divmod(surface, 6)
    axis = face // 2
    sign = np.where(face % 2 == 1, np.float32(1.0), np.float32(-1.0))
    points = [np.float32(origin[k]) + t * d[k] for k in range(3)]
    centres = scene.centres.astype(np.float32)
    rel = [points[k] - centres[obj, k] for k in range(3)]
    cos = scene.rotations[:, 0, 0].astype(np.float32)[obj]
    sin = scene.rotations[:, 1, 0].astype(np.float32)[obj]
    local_x = cos * rel[0] + sin * rel[1]
    local_y = -sin * rel[0] + cos * rel[1]
    u = np.where(axis == 0, local_y, local_x)
    v = np.where(axis == 2, local_y, rel[2])
    zero = np.float32(0.0)
    normal = (
        sign * np.where(axis == 0, cos, np.where(axis == 1, -sin, zero)),
        sign * np.where(axis == 0, sin, np.where(axis == 1, cos, zero)),
        sign * (axis == 2),
    )

    texels_per_m = scene.surface_texels_per_m[surface]
    offset = scene.surface_offset[surface]
    ray_length = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    cos_view = np.abs(normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2]) / ray_length
    cos_view = np.clip(cos_view, np.float32(0.05), np.float32(1.0))
    footprint = np.maximum(t * ray_length * texels_per_m / np.float32(focal), np.float32(1e-6))
    lod = np.log2(footprint) - np.float32(0.5) * np.log2(cos_view)
    albedo = scene.atlas.sample(
        scene.surface_texture[surface], u * texels_per_m + offset[:, 0], v * texels_per_m + offset[:, 1], lod
    )

    to_light = [np.float32(scene.light[k]) - points[k] for k in range(3)]
    dist = np.sqrt(to_light[0] ** 2 + to_light[1] ** 2 + to_light[2] ** 2)
    lambert = np.maximum(
        (normal[0] * to_light[0] + normal[1] * to_light[1] + normal[2] * to_light[2]) / dist, 0
    )
    irradiance = scene.ambient + scene.diffuse * lambert / (1.0 + (dist / np.float32(scene.falloff)) ** 2)
    return albedo * (np.float32(EXPOSURE) * irradiance.astype(np.float32))[:, None]


def _edge_pixels(surface: np.ndarray) -> np.ndarray:
    """Pixels whose 4-neighbourhood shows another surface (silhouettes and creases)."""
    edge = np.zeros(surface.shape, dtype=bool)
    dh = surface[:, 1:] != surface[:, :-1]
    dv = surface[1:, :] != surface[:-1, :]
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    return edge


def _supersample_edges(
    scene: Scene, camera: PinholeCamera, T_wc: np.ndarray, edge: np.ndarray, focal: float, lens_k1: float
) -> np.ndarray:
    """Mean radiance (E, 3) of four rotated-grid sub-pixel rays for each edge pixel."""
    rows, cols = np.nonzero(edge)
    u = (cols[None, :] + RGSS_OFFSETS[:, 0][:, None]).reshape(-1)
    v = (rows[None, :] + RGSS_OFFSETS[:, 1][:, None]).reshape(-1)
    d = _rotate_rays(T_wc[:3, :3], *_slopes(camera, u, v, lens_k1))
    origin = T_wc[:3, 3]
    t, surface = cast_rays(scene, origin, d)
    radiance = shade(scene, origin, d, t, surface, focal)
    return radiance.reshape(len(RGSS_OFFSETS), len(rows), 3).mean(axis=0)


def _checked_pose(T_wc: np.ndarray) -> np.ndarray:
    T_wc = np.asarray(T_wc, dtype=np.float64)
    if T_wc.shape != (4, 4) or not np.all(np.isfinite(T_wc)):
        raise ValueError(f'render_frame: T_wc must be a finite 4x4 pose, got shape {T_wc.shape}')
    return T_wc


def render_radiance(
    scene: Scene, camera: PinholeCamera, T_wc: np.ndarray, *, antialias: bool = True, lens_k1: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(radiance (H, W, 3) float32 grey levels, depth, surface id)`` of one instantaneous
    view: what reaches the sensor before its exposure, noise and quantisation."""
    T_wc = _checked_pose(T_wc)
    depth, surface, d = cast_camera(scene, camera, T_wc, lens_k1)
    focal = float(np.sqrt(camera.fx * camera.fy))
    H, W = depth.shape
    flat = tuple(c.reshape(-1) for c in d)
    radiance = shade(scene, T_wc[:3, 3], flat, depth.reshape(-1), surface.reshape(-1), focal).reshape(H, W, 3)
    if antialias:
        edge = _edge_pixels(surface)
        if edge.any():
            radiance[edge] = _supersample_edges(scene, camera, T_wc, edge, focal, lens_k1)
    return radiance, depth, surface


def render_frame(
    scene: Scene,
    camera: PinholeCamera,
    T_wc: np.ndarray,
    *,
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
    antialias: bool = True,
    gain: float = 1.0,
    exposure_poses: np.ndarray | None = None,
    row_weights: np.ndarray | None = None,
    lens_k1: float = 0.0,
) -> RenderedFrame:
    """Render one view of ``scene`` from camera-to-world pose ``T_wc``.

    Depth is the exact z-depth at each pixel centre. Colour is Lambertian shading of the
    surface texture, supersampled on silhouettes when ``antialias``, plus Gaussian sensor
    noise of ``noise_sigma`` grey levels drawn from ``rng`` (required when noise > 0, so the
    caller controls determinism), rounded and clipped to uint8.

    ``exposure_poses`` (K, 4, 4): the camera's poses while the shutter is open; the colour is
    the mean of the K views (motion blur), the depth still that of ``T_wc`` (the stamp's
    pose, which the pipeline is told). ``row_weights`` (H, K): each row's own mix of the K
    views instead of their mean (a rolling shutter: each row exposed at its own time; rows sum
    to 1). ``gain`` scales the colour before noise and clipping
    (a frame's auto-exposure), so bright surfaces saturate as on a sensor. ``lens_k1``: the
    lens's radial distortion (plumb_bob ``k1``); depth and colour are both seen through it.
    """
    if noise_sigma > 0 and rng is None:
        raise ValueError('render_frame: noise_sigma > 0 needs an rng (a numpy Generator)')
    if exposure_poses is not None and len(exposure_poses):
        # The image is made of the exposure's views; of the stamp's pose only its geometry,
        # which the view at the stamp (the middle one of an odd count) has already cast.
        T_wc = _checked_pose(T_wc)
        renders = [
            render_radiance(scene, camera, pose, antialias=antialias, lens_k1=lens_k1)
            for pose in exposure_poses
        ]
        at_stamp = [r for pose, r in zip(exposure_poses, renders, strict=True) if np.array_equal(pose, T_wc)]
        depth, surface = at_stamp[0][1:] if at_stamp else cast_camera(scene, camera, T_wc, lens_k1)[:2]
        views = np.stack([r[0] for r in renders])
        if row_weights is None:
            radiance = views.mean(axis=0)
        else:
            radiance = np.einsum('khwc,hk->hwc', views, np.asarray(row_weights, dtype=np.float32))
    else:
        radiance, depth, surface = render_radiance(scene, camera, T_wc, antialias=antialias, lens_k1=lens_k1)
    if gain != 1.0:
        radiance *= np.float32(gain)
    if noise_sigma > 0:
        radiance += rng.standard_normal(radiance.shape, dtype=np.float32) * np.float32(noise_sigma)
    rgb = np.clip(np.rint(radiance), 0, 255).astype(np.uint8)
    return RenderedFrame(rgb=rgb, depth=depth, surface=surface, textured=scene.surface_textured[surface])
