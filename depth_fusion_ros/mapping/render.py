"""A picture of a map: its coloured surface points splatted into a virtual camera (numpy).

The view is a keyframe's camera pulled back along its optical axis, so the picture looks
like what the camera saw, with the whole mapped area in frame. A z-buffer keeps the nearest
point per pixel; points are splatted as small squares. matplotlib only saves the panels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import PinholeCamera
from .surface import SurfaceMesh


def viewpoint(T_wc: np.ndarray, pull_back: float = 0.5) -> np.ndarray:
    """``T_wc`` moved ``pull_back`` metres backwards along its optical axis."""
    T = np.array(T_wc, dtype=np.float64)
    T[:3, 3] -= pull_back * T[:3, 2]
    return T


def splat(mesh: SurfaceMesh, T_wc: np.ndarray, camera: PinholeCamera, radius: int = 1) -> np.ndarray:
    """HxWx3 uint8 image of the mesh vertices seen from ``T_wc`` (white where nothing)."""
    image = np.full((camera.height, camera.width, 3), 255, np.uint8)
    if mesh.is_empty:
        return image
    R, t = T_wc[:3, :3], T_wc[:3, 3]
    cam = (mesh.vertices.astype(np.float64) - t) @ R
    front = cam[:, 2] > 0.05
    cam, colours = cam[front], mesh.colours[front]
    u = np.round(cam[:, 0] / cam[:, 2] * camera.fx + camera.cx).astype(np.int64)
    v = np.round(cam[:, 1] / cam[:, 2] * camera.fy + camera.cy).astype(np.int64)
    order = np.argsort(-cam[:, 2])  # far first: nearer points overwrite them
    u, v, colours = u[order], v[order], colours[order]
    for du in range(-radius, radius + 1):
        for dv in range(-radius, radius + 1):
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < camera.width) & (vv >= 0) & (vv < camera.height)
            image[vv[ok], uu[ok]] = colours[ok]
    return image


def map_figure(
    meshes: dict[str, SurfaceMesh], T_wc: np.ndarray, camera: PinholeCamera, path: Path, title: str = ''
) -> Path:
    """One panel per map, all from the same viewpoint; written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    # 1.5x the image size at the same focal length: a wider view than the keyframe's.
    w, h = camera.width * 3 // 2, camera.height * 3 // 2
    view = PinholeCamera(w, h, camera.fx, camera.fy, (w - 1) / 2, (h - 1) / 2)
    pose = viewpoint(T_wc)
    fig, axes = plt.subplots(1, len(meshes), figsize=(4.2 * len(meshes), 3.5), squeeze=False)
    for ax, (name, mesh) in zip(axes[0], meshes.items(), strict=True):
        ax.imshow(splat(mesh, pose, view))
        ax.set_title(f'{name} ({len(mesh.vertices)} points)', fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
