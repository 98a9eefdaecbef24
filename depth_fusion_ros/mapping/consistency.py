"""Multi-keyframe depth consistency before TSDF integration (the map's fixed lag).

A fused depth image is right near its multi-view points and drifts with the single-view
prior elsewhere. Its confidence says how far a pixel is from those points, not whether it is
right, so a confidence threshold trades completeness for accuracy. Depth that is wrong is,
however, rarely wrong *the same way* in another keyframe (another view, another set of
multi-view points, another prior error), while the true surface is seen alike by all. So a
pixel is integrated only where at least ``consistency_views`` of the keyframes within
``consistency_span`` keyframes before and after it see the same surface: its 3-D point,
projected into the other keyframe, lands on a depth within ``consistency_tolerance``
(relative) of its own. This is the geometric consistency test of multi-view stereo depth-map
fusion (e.g. COLMAP's fusion, Gipuma), on the fused keyframes.

Measured (docs/mapping.md): on the synthetic room and TUM fr1_xyz it gives a map both more
accurate and more complete than the confidence threshold alone.

The test needs the keyframes that follow, so :class:`ConsistentMap` integrates a keyframe
once ``consistency_span`` later ones have arrived (the map lags that many keyframes) and
:meth:`ConsistentMap.flush` integrates the rest (checked against what is there) before a mesh
is saved. A keyframe that has no other keyframe to be checked against at all (a stream of one)
is integrated as it is and counted in ``unchecked``.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from ..camera import PinholeCamera
from .config import MapConfig

log = logging.getLogger(__name__)


@dataclass
class _Keyframe:
    depth: torch.Tensor  # on the map's device, converted once and reused by every check
    T_wc: np.ndarray
    camera: PinholeCamera
    confidence: np.ndarray | None
    rgb: np.ndarray | None
    key: object = None
    integrated: bool = False


def agreeing_views(
    d: torch.Tensor,
    T_wc: np.ndarray,
    others: list[tuple[torch.Tensor, np.ndarray]],
    camera: PinholeCamera,
    tolerance: float,
) -> torch.Tensor:
    """Per pixel of ``d``: in how many of ``others`` (``(depth, T_wc)`` of the same camera, on
    the same device) its point lands on a depth within ``tolerance`` (relative to the projected
    depth): ``(H, W)`` int32 counts.

    Nearest-pixel lookup; points behind the other camera or outside its image count as not
    consistent (no evidence either way, and none is taken); pixels without depth count 0.

    Every pixel is projected (a fused keyframe has depth almost everywhere, so selecting the
    pixels with depth first costs more than it saves) and those without depth are zeroed at
    the end. Per other keyframe a dozen elementwise passes; one batched nearest
    ``grid_sample`` and one comparison for all of them."""
    h, w = d.shape
    dev = d.device
    if not others:
        return torch.zeros((h, w), dtype=torch.int32, device=dev)
    n = h * w
    z_k = d.reshape(-1)
    u = torch.arange(w, device=dev, dtype=torch.float32).sub_(camera.cx)
    v = torch.arange(h, device=dev, dtype=torch.float32).sub_(camera.cy)
    x_k = (u[None] * d).div_(camera.fx).reshape(-1)
    y_k = (v[:, None] * d).div_(camera.fy).reshape(-1)
    T_k = np.asarray(T_wc, np.float64)
    # Pixel -> grid_sample's [-1, 1] (align_corners: -1 and 1 are the first and last pixel
    # centres); 'nearest' is the nearest-pixel lookup, and outside the image it reads 0, which
    # agrees with no positive depth.
    sx, sy = 2 * camera.fx / (w - 1), 2 * camera.fy / (h - 1)
    ox, oy = 2 * camera.cx / (w - 1) - 1, 2 * camera.cy / (h - 1) - 1
    k = len(others)
    planes = torch.empty((k, 2, n), dtype=torch.float32, device=dev)  # grid x and y, planar
    z = torch.empty((k, n), dtype=torch.float32, device=dev)
    for i, (_, other_T) in enumerate(others):
        rel = np.linalg.inv(np.asarray(other_T, np.float64)) @ T_k  # keyframe -> other camera
        # Rows of the rigid motion as scalars: three contiguous (N,) passes per coordinate
        # (a (N, 3) x (3, 3) product is slower on CPU than these).
        _affine(rel[2], x_k, y_k, z_k, out=z[i])
        torch.div(_affine(rel[0], x_k, y_k, z_k, out=planes[i, 0]), z[i], out=planes[i, 0])
        torch.div(_affine(rel[1], x_k, y_k, z_k, out=planes[i, 1]), z[i], out=planes[i, 1])
        planes[i, 0].mul_(sx).add_(ox)
        planes[i, 1].mul_(sy).add_(oy)
    images = torch.stack([o for o, _ in others])[:, None]  # (K, 1, H, W)
    # The (K, 1, N, 2) grid as a strided view of the planes: grid_sample reads it in place.
    grid = planes.permute(0, 2, 1)[:, None]
    seen = F.grid_sample(images, grid, mode='nearest', align_corners=True).reshape(k, n)
    agree = (z > 0) & ((seen - z).abs_() <= tolerance * z)  # NaN compares False
    count = agree.sum(dim=0, dtype=torch.int32)
    return count.mul_(z_k > 0).reshape(h, w)  # NaN > 0 is False


def _affine(
    row: np.ndarray, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, out: torch.Tensor
) -> torch.Tensor:
    """``row[0] x + row[1] y + row[2] z + row[3]`` (one row of a 4x4 rigid motion), into ``out``."""
    torch.mul(x, float(row[0]), out=out)
    return out.add_(y, alpha=float(row[1])).add_(z, alpha=float(row[2])).add_(float(row[3]))


class ConsistentMap:
    """A TSDF map (any engine) that integrates each keyframe's consistent pixels only.

    It offers the engine's interface (``integrate``, ``mesh``, ``n_blocks``, ...); ``integrate``
    queues the keyframe and integrates the ones whose ``consistency_span`` successors are in.
    ``on_integrated(key, depth, T_wc, camera, confidence, rgb)`` is told of every keyframe as it
    goes into the engine (its depth after the test, numpy): what a rebuild at corrected poses
    integrates again (mapping/keyframe_store.py).
    """

    def __init__(self, engine: object, config: MapConfig) -> None:
        self.engine = engine
        self.on_integrated: Callable[..., None] | None = None
        self.config = config
        self.span = int(config.consistency_span)
        self._window: deque[_Keyframe] = deque(maxlen=2 * self.span + 1)
        #: Keyframes integrated without a check (no other keyframe to check against).
        self.unchecked = 0
        #: Pixels with depth that the check left out, and that it kept, over the run.
        self.pixels_rejected = 0
        self.pixels_kept = 0
        self._device = torch.device(config.device)
        #: The torch engine takes the masked depth as a tensor on the device (no host round
        #: trip); any other engine gets numpy.
        self._tensors = bool(getattr(engine, 'accepts_tensors', False))

    def __getattr__(self, name: str) -> object:  # n_blocks, memory_bytes, evicted_blocks, name...
        return getattr(self.engine, name)

    def close(self) -> None:
        """Release what the engine holds outside memory (the torch engine's disk archive)."""
        self.engine.close()

    @property
    def pending(self) -> int:
        """Keyframes received and not yet integrated (waiting for their successors)."""
        return sum(not k.integrated for k in self._window)

    def integrate(
        self,
        depth: np.ndarray,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
        key: object = None,
    ) -> int:
        """Queue one keyframe; integrate the one ``span`` keyframes back. Returns voxels updated.

        With ``consistency_span`` 0 the keyframe goes straight to the engine, every pixel.
        ``key`` (e.g. its stamp) is handed to ``on_integrated`` with it."""
        if self.span == 0:
            return self._to_engine(key, depth, T_wc, camera, confidence, rgb)
        d = torch.as_tensor(depth, dtype=torch.float32, device=self._device)
        if d.shape != (camera.height, camera.width):
            size = f'{camera.width}x{camera.height}'
            raise ValueError(f'depth is {d.shape[1]}x{d.shape[0]}, camera is {size}')
        if len(self._window) == self._window.maxlen and not self._window[0].integrated:
            self._integrate_at(0)  # about to leave the window: integrate with what it had
        self._window.append(_Keyframe(d, np.asarray(T_wc, np.float64), camera, confidence, rgb, key))
        target = len(self._window) - 1 - self.span
        return self._integrate_at(target) if target >= 0 else 0

    def flush(self) -> int:
        """Integrate every waiting keyframe, checked against the keyframes there are."""
        return sum(self._integrate_at(i) for i in range(len(self._window)) if not self._window[i].integrated)

    def mesh(self) -> object:
        """The engine's mesh of what is integrated so far (waiting keyframes are not in it)."""
        return self.engine.mesh()

    def window_keyframes(self) -> list[tuple[object, np.ndarray]]:
        """``(key, T_wc)`` of the keyframes in the test's window (waiting, or checked against)."""
        return [(k.key, k.T_wc) for k in self._window]

    def waiting_keys(self) -> list[object]:
        """Keys of the window's keyframes not yet integrated (moving them moves where they go)."""
        return [k.key for k in self._window if not k.integrated]

    def move_window(self, pose_of: Callable[[object, np.ndarray], np.ndarray]) -> None:
        """Give every keyframe of the window the pose ``pose_of(key, T_wc)`` (a corrected
        trajectory moved it: the waiting ones are then checked and integrated there, against
        the others where they now are)."""
        for k in self._window:
            k.T_wc = np.asarray(pose_of(k.key, k.T_wc), np.float64)

    def _to_engine(
        self,
        key: object,
        depth: np.ndarray | torch.Tensor,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: np.ndarray | None,
        rgb: np.ndarray | None,
    ) -> int:
        updated = self.engine.integrate(depth, T_wc, camera, confidence=confidence, rgb=rgb)
        if self.on_integrated is not None:
            host = depth.cpu().numpy() if isinstance(depth, torch.Tensor) else depth
            self.on_integrated(key, host, T_wc, camera, confidence, rgb)
        return updated

    def _integrate_at(self, index: int) -> int:
        keyframe = self._window[index]
        if keyframe.integrated:
            return 0
        keyframe.integrated = True
        others = [(k.depth, k.T_wc) for i, k in enumerate(self._window) if i != index]
        depth = keyframe.depth
        if others:
            need = min(int(self.config.consistency_views), len(others))
            cfg = self.config
            count = agreeing_views(depth, keyframe.T_wc, others, keyframe.camera, cfg.consistency_tolerance)
            valid = (depth > 0) & (depth < float('inf'))  # finite and positive
            keep = valid & (count >= need)
            kept, with_depth = torch.stack((keep.sum(), valid.sum())).tolist()  # one device sync
            self.pixels_kept += kept
            self.pixels_rejected += with_depth - kept
            depth = torch.where(keep, depth, float('nan'))
        else:
            self.unchecked += 1
            log.info('map: a keyframe with no other keyframe to check it against is integrated unchecked')
        if not self._tensors:
            depth = depth.cpu().numpy()
        return self._to_engine(
            keyframe.key, depth, keyframe.T_wc, keyframe.camera, keyframe.confidence, keyframe.rgb
        )
