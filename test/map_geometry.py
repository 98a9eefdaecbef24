"""Distance from points to the known surface of a synthetic room (test helper, no ROS)."""

from __future__ import annotations

import numpy as np


def room_surface_distance(scene, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) from each point to the nearest room face or furniture box face.

    Object 0 of a synthetic ``Scene`` is the room (seen from inside), the others solid boxes;
    each is an oriented box, and the distance to a box's surface is ``|sdf_box|``.
    """
    best = np.full(len(points), np.inf)
    for centre, half, rotation in zip(scene.centres, scene.halves, scene.rotations, strict=True):
        q = np.abs((points - centre) @ rotation) - half  # box frame, folded into one octant
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        best = np.minimum(best, np.abs(outside + inside))
    return best
