"""Choose, for a keyframe, the overlapping frames that give the multi-view search useful parallax.

What makes a good neighbour (paper §III-A, "n overlapping frames"):

* **parallax**: the baseline relative to the scene depth, ``r = |c_o - c_k| / scene_depth``. The
  depth uncertainty of a match is proportional to ``1 / r``, so too short a baseline is
  useless; too long a baseline changes appearance (occlusions, perspective) and lengthens
  the epipolar search. Frames are ranked by how close ``r`` is to ``target_parallax`` (in
  log scale, so half and double the target are equally good);
* **bounded rotation** (``max_rotation_deg``): the patch cost assumes a patch keeps its shape;
* **image overlap** (``min_overlap``): the fraction of a grid of keyframe pixels, placed at the
  scene depth, that project inside the other image. A frame looking elsewhere is rejected.

Chosen neighbours are kept apart (``min_separation`` of the target baseline) so that they
do not all sit on the same side at the same distance: diverse baselines and epipolar
directions disambiguate repetitive texture and edges parallel to one epipolar line.

Modes: ``online`` picks among the ``window`` frames *before* the keyframe (all a node has);
``offline`` among the frames within ``window`` on either side (evaluation). Frames with
(almost) zero baseline - pure rotation - are used only when nothing better overlaps, and
a warning says so, because they carry no depth information.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..camera import PinholeCamera
from ..geometry import validate_pose, validate_poses

log = logging.getLogger(__name__)

MODES = ('online', 'offline')
#: Camera used for the overlap test when the caller gives none (60 deg horizontal field of view, 4:3).
_GENERIC_CAMERA = PinholeCamera(320, 240, 277.1, 277.1, 159.5, 119.5)


@dataclass(frozen=True)
class NeighbourConfig:
    """Parameters of neighbour selection (defaults for hand-held indoor sequences at 30 Hz)."""

    #: Frames considered: the previous ``window`` (online) or ``window`` on each side (offline).
    window: int = 30
    #: Typical scene depth (m) that turns a baseline into parallax and places the overlap grid.
    scene_depth: float = 1.5
    #: Preferred baseline / scene depth.
    target_parallax: float = 0.08
    #: Below this baseline / depth a frame counts as zero baseline (pure rotation).
    min_parallax: float = 0.005
    #: Above this baseline / depth a frame is not used (appearance changes too much).
    max_parallax: float = 0.3
    #: Largest rotation between keyframe and neighbour (degrees).
    max_rotation_deg: float = 30.0
    #: Smallest fraction of the keyframe that must be visible in the neighbour.
    min_overlap: float = 0.6
    #: Chosen neighbours are at least this fraction of the target baseline apart (when possible).
    min_separation: float = 0.5

    def validate(self) -> None:
        if self.window < 1:
            raise ValueError(f'neighbours.window must be >= 1, got {self.window}')
        if not (self.scene_depth > 0 and self.target_parallax > 0):
            raise ValueError('neighbours.scene_depth and neighbours.target_parallax must be positive')
        if not (0 <= self.min_parallax < self.max_parallax):
            raise ValueError(
                'need 0 <= neighbours.min_parallax < neighbours.max_parallax, '
                f'got {self.min_parallax} and {self.max_parallax}'
            )
        if not (0 <= self.min_overlap <= 1):
            raise ValueError(f'neighbours.min_overlap must be in [0, 1], got {self.min_overlap}')


@dataclass(frozen=True)
class NeighbourCandidate:
    """Why a frame was (not) chosen: its parallax, rotation and overlap with the keyframe."""

    index: int
    parallax: float
    rotation_deg: float
    overlap: float


def overlap_fraction(T_ok: np.ndarray, camera: PinholeCamera, depth: float, grid: int = 12) -> float:
    """Fraction of a ``grid x grid`` lattice of keyframe pixels at ``depth`` seen by the other camera."""
    return float(overlap_fractions(T_ok[None, :3, :3], T_ok[None, :3, 3], camera, depth, grid)[0])


def overlap_fractions(
    R_ok: np.ndarray, t_ok: np.ndarray, camera: PinholeCamera, depth: float, grid: int = 12
) -> np.ndarray:
    """:func:`overlap_fraction` of K other cameras at once (rotations (K, 3, 3), translations
    (K, 3) from keyframe to other-camera coordinates), one batched projection of the lattice."""
    u = np.linspace(0, camera.width - 1, grid)
    v = np.linspace(0, camera.height - 1, grid)
    uu, vv = np.meshgrid(u, v)
    pts = np.stack(((uu - camera.cx) / camera.fx * depth, (vv - camera.cy) / camera.fy * depth), axis=-1)
    pts = np.concatenate((pts, np.full((*uu.shape, 1), depth)), axis=-1).reshape(-1, 3)
    p_o = pts @ np.swapaxes(R_ok, 1, 2) + t_ok[:, None, :]  # (K, grid², 3)
    z = p_o[..., 2]
    in_front = z > 1e-6
    with np.errstate(divide='ignore', invalid='ignore'):
        uo = camera.fx * p_o[..., 0] / z + camera.cx
        vo = camera.fy * p_o[..., 1] / z + camera.cy
    inside = in_front & (uo >= 0) & (uo <= camera.width - 1) & (vo >= 0) & (vo <= camera.height - 1)
    return inside.mean(axis=1)


def window_indices(num_frames: int, key: int, mode: str, window: int) -> list[int]:
    """Frame indices a keyframe may take neighbours from."""
    if mode == 'online':
        return list(range(max(0, key - window), key))
    if mode == 'offline':
        return [i for i in range(max(0, key - window), min(num_frames, key + window + 1)) if i != key]
    raise ValueError(f'neighbour mode must be one of {MODES}, got {mode!r}')


def describe_candidates(
    poses: np.ndarray, key: int, indices: list[int], camera: PinholeCamera, config: NeighbourConfig
) -> list[NeighbourCandidate]:
    """Parallax, rotation and overlap of each candidate frame against the keyframe.

    All candidates at once (one batched relative pose, angle and lattice projection): a node
    asks this for every keyframe over its 30-frame window, on its executor thread, and the
    loop over candidates it replaces took 20-40 ms of that thread (and of the GIL) a keyframe.
    """
    T_wk = validate_pose(poses[key], f'pose of keyframe {key}')
    if not indices:
        return []
    others = validate_poses(np.asarray(poses)[indices], [f'pose of frame {i}' for i in indices])
    R_wo, t_wo = others[:, :3, :3], others[:, :3, 3]
    R_ow = np.swapaxes(R_wo, 1, 2)
    R_ok = R_ow @ T_wk[:3, :3]  # T_ok = inv(T_wo) @ T_wk
    t_ok = (R_ow @ (T_wk[:3, 3] - t_wo)[:, :, None])[:, :, 0]
    baseline = np.linalg.norm(t_wo - T_wk[:3, 3], axis=1)
    cosine = (np.trace(R_ok, axis1=1, axis2=2) - 1.0) / 2.0
    rotation = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    overlap = overlap_fractions(R_ok, t_ok, camera, config.scene_depth)
    return [
        NeighbourCandidate(
            index=i,
            parallax=float(baseline[j]) / config.scene_depth,
            rotation_deg=float(rotation[j]),
            overlap=float(overlap[j]),
        )
        for j, i in enumerate(indices)
    ]


def _pick_spread(
    ranked: list[NeighbourCandidate], centres: dict[int, np.ndarray], n: int, separation: float
) -> list[int]:
    """Greedy: best-ranked first, skipping frames within ``separation`` (m) of a chosen one;
    fill up with the skipped ones if fewer than ``n`` remain."""
    chosen: list[int] = []
    skipped: list[int] = []
    for c in ranked:
        if len(chosen) == n:
            break
        if all(np.linalg.norm(centres[c.index] - centres[j]) >= separation for j in chosen):
            chosen.append(c.index)
        else:
            skipped.append(c.index)
    chosen += skipped[: n - len(chosen)]
    return chosen


def select_neighbours(
    poses: np.ndarray,
    key: int,
    n: int = 4,
    mode: str = 'online',
    camera: PinholeCamera | None = None,
    config: NeighbourConfig | None = None,
    warn: Callable[[str], None] | None = None,
) -> list[int]:
    """Indices (into ``poses``, camera-to-world (N, 4, 4)) of up to ``n`` neighbours of frame ``key``.

    Returns fewer (possibly none, e.g. the first frame online) when not enough frames overlap.
    A NaN or non-orthonormal pose in the window raises ``geometry.PoseError`` naming the frame.
    Zero-baseline-only neighbours are reported through ``warn`` (default: this module's logger);
    a node passes its throttled counter, since a robot standing still triggers it every keyframe.
    """
    config = config or NeighbourConfig()
    config.validate()
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f'poses must be (N, 4, 4), got {poses.shape}')
    if not (0 <= key < len(poses)):
        raise ValueError(f'keyframe index {key} outside the {len(poses)} poses')
    if n < 1:
        raise ValueError(f'number of neighbours must be >= 1, got {n}')
    camera = camera or _GENERIC_CAMERA
    indices = window_indices(len(poses), key, mode, config.window)
    candidates = describe_candidates(poses, key, indices, camera, config)
    usable = [
        c
        for c in candidates
        if c.rotation_deg <= config.max_rotation_deg
        and c.overlap >= config.min_overlap
        and c.parallax <= config.max_parallax
    ]
    with_parallax = [c for c in usable if c.parallax >= config.min_parallax]
    ranked = sorted(
        with_parallax, key=lambda c: (abs(math.log(c.parallax / config.target_parallax)), abs(c.index - key))
    )
    centres = {c.index: poses[c.index][:3, 3] for c in usable}
    separation = config.min_separation * config.target_parallax * config.scene_depth
    chosen = _pick_spread(ranked, centres, n, separation)
    if len(chosen) < n:
        flat = sorted((c for c in usable if c.parallax < config.min_parallax), key=lambda c: -c.parallax)
        chosen += [c.index for c in flat[: n - len(chosen)]]
        if chosen and not with_parallax:
            message = (
                f'every overlapping frame has (almost) zero baseline (< {config.min_parallax:.3g} x '
                f'scene depth, e.g. a pure rotation): its multi-view depth will be unreliable'
            )
            if warn is None:
                log.warning('keyframe %d (neighbours %s): %s', key, chosen, message)
            else:
                warn(message)
    if not chosen:
        log.debug('keyframe %d: no overlapping neighbour among %d frames (%s mode)', key, len(indices), mode)
    return chosen


def neighbour_table(
    poses: np.ndarray,
    n: int = 4,
    mode: str = 'offline',
    camera: PinholeCamera | None = None,
    config: NeighbourConfig | None = None,
    keys: list[int] | None = None,
) -> dict[int, list[int]]:
    """:func:`select_neighbours` for every keyframe of a sequence (``keys``, default all frames)."""
    keys = list(range(len(poses))) if keys is None else keys
    return {k: select_neighbours(poses, k, n, mode, camera, config) for k in keys}
