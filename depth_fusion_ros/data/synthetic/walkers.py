"""Moving objects: person-sized boxes that walk back and forth across the camera's view.

Multi-view depth assumes a static world; a robot's camera sees people walk by. A walker
is a textured box of a standing person's size (0.5 x 0.3 x 1.7 m) on the floor, on a line
across the nominal view ``WALKER_DISTANCE`` m ahead of the nominal camera position (walker
``k`` another ``WALKER_SPACING`` m further), walking at ``SynthConfig.walker_speed`` m/s and
turning back ``WALKER_REACH`` m either side of the view's centre line. Its pixels move as no
static point at any depth would, and the ground-truth depth shows it where it is.

The walkers are the last objects of the scene (``build_scene`` appends them after the
furniture, so a config without walkers draws the same room as before); :func:`scene_at`
moves them to a frame's time.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from .config import SynthConfig
from .trajectory import Trajectory

if TYPE_CHECKING:  # scene.py imports this module to place the walkers
    from .scene import Scene

#: Half extents (m) of a walker: 0.5 m wide, 0.3 m deep, 1.7 m tall.
WALKER_HALF = np.array([0.25, 0.15, 0.85])
#: Distance (m) of the first walker's line ahead of the nominal camera position.
WALKER_DISTANCE = 1.6
#: Extra distance (m) of each further walker's line.
WALKER_SPACING = 0.8
#: How far (m) either side of the view's centre line a walker goes before it turns back.
WALKER_REACH = 1.2


def _axes(trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors in the floor plane: ahead along the nominal view, and across it."""
    ahead = np.asarray(trajectory.view_target, dtype=np.float64) - trajectory.view_origin
    ahead[2] = 0.0
    ahead /= np.linalg.norm(ahead)
    return ahead, np.cross(ahead, (0.0, 0.0, 1.0))


def walker_centres(cfg: SynthConfig, trajectory: Trajectory, index: int) -> np.ndarray:
    """(walkers, 3) centres of the walkers at frame ``index`` (time ``index / fps``)."""
    ahead, across = _axes(trajectory)
    k = np.arange(cfg.walkers)[:, None]
    # A triangle wave between -reach and +reach at walker_speed, walker k a quarter period
    # later than walker k - 1 (so they do not walk in step).
    u = (cfg.walker_speed * (index / cfg.fps) / WALKER_REACH + 1.0 + k) % 4.0
    offset = WALKER_REACH * np.where(u <= 2.0, u - 1.0, 3.0 - u)
    centres = trajectory.view_origin + ahead * (WALKER_DISTANCE + k * WALKER_SPACING) + across * offset
    centres[:, 2] = WALKER_HALF[2]  # standing on the floor
    return centres


def walker_yaw(trajectory: Trajectory) -> float:
    """The walkers' yaw: their broad side faces the nominal camera."""
    _, across = _axes(trajectory)
    return float(np.arctan2(across[1], across[0]))


def scene_at(scene: Scene, cfg: SynthConfig, trajectory: Trajectory, index: int) -> Scene:
    """``scene`` with its walkers (its last ``cfg.walkers`` objects) where they are at frame
    ``index``; the scene itself when there are none."""
    if not cfg.walkers:
        return scene
    centres = scene.centres.copy()
    centres[-cfg.walkers :] = walker_centres(cfg, trajectory, index)
    return replace(scene, centres=centres, _corners=None)
