"""Ground-truth depth from a depth camera moved into the colour camera the images come from.

Why: an RGB-D dataset whose two cameras are not registered (7-Scenes: a Kinect's infrared
depth camera, fx 585, beside its colour camera, about 525) gives the depth on the depth
camera's pixel grid. The depth is the ground truth for the colour image, so it must be seen
from the colour camera. With the same optical centre a point keeps its z and only its pixel
moves (a remap). With the centres a baseline ``b`` apart, a point at depth ``z`` moves a further
``f * b / z`` pixels: on a Kinect (2.5 cm) 13 px at 1 m and 4 px at 3 m at 640x480, so a near
object's outline lands pixels off the far wall's unless the depth is projected from its own
centre. On 7-Scenes the depth edges line up with the colour edges best with the colour camera
2.5 cm along the depth camera's x axis (``scripts/diag/depth_colour_baseline.py``; docs/data.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import PinholeCamera


def register_depth(
    depth: np.ndarray,
    depth_camera: PinholeCamera,
    colour_camera: PinholeCamera,
    colour_centre: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """``depth`` (metres, the depth camera's grid; NaN or 0 where none) seen from the colour
    camera, on its grid (NaN where it has none). ``colour_centre``: the colour camera's optical
    centre in the depth camera's optical frame (m); both cameras face the same way. At the
    same centre, a nearest-neighbour remap; apart, each depth pixel's point projected into the
    colour camera, the nearest surface kept where several land on one pixel."""
    if not any(colour_centre):
        u, v = colour_camera.pixel_grid()
        d, c = depth_camera, colour_camera
        map_x = (d.cx + d.fx * (u - c.cx) / c.fx).astype(np.float32)
        map_y = (d.cy + d.fy * (v - c.cy) / c.fy).astype(np.float32)
        return cv2.remap(
            depth, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=float('nan')
        )
    return _projected(depth, depth_camera, colour_camera, np.asarray(colour_centre, dtype=np.float64))


def _projected(
    depth: np.ndarray, depth_camera: PinholeCamera, colour_camera: PinholeCamera, centre: np.ndarray
) -> np.ndarray:
    """Each depth pixel's point projected into the colour camera at ``centre``; a z-buffer by
    sorting (per colour pixel, the nearest point first)."""
    points = depth_camera.backproject(depth)[np.isfinite(depth) & (depth > 0)] - centre
    points = points[points[:, 2] > 0]
    uv, z = colour_camera.project(points)
    uc, vc = np.rint(uv).astype(np.int64).T
    w, h = colour_camera.width, colour_camera.height
    inside = (uc >= 0) & (uc < w) & (vc >= 0) & (vc < h)
    pixel, z = vc[inside] * w + uc[inside], z[inside]
    order = np.lexsort((z, pixel))
    pixel, z = pixel[order], z[order]
    first = np.ones(len(pixel), dtype=bool)
    first[1:] = pixel[1:] != pixel[:-1]
    out = np.full(h * w, np.nan, dtype=np.float32)
    out[pixel[first]] = z[first]
    return out.reshape(h, w)
