"""Map accuracy and completeness against a reference map (no ROS).

Both maps are meshes; each is densified to points about a quarter voxel apart (barycentric
samples of every triangle) so that distances measure the surfaces, not the vertex spacing.

* **accuracy**: distance from every point of the map to the nearest point of the reference
  surface (median, mean): is what the map says there true?
* **completeness**: the share of reference surface points with a map point within 5 cm /
  10 cm: how much of the true surface does the map have?

Every map point counts for accuracy, also where the reference has no data (the map cannot be
checked there; it is not given the benefit of the doubt).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .surface import SurfaceMesh

#: Barycentric subdivisions per triangle edge when densifying a mesh.
SUBDIVISIONS = 4


def surface_samples(mesh: SurfaceMesh, subdivisions: int = SUBDIVISIONS) -> np.ndarray:
    """Points on the mesh surface: its vertices plus a barycentric grid on every triangle."""
    v = mesh.vertices.astype(np.float64)
    if len(mesh.triangles) == 0:
        return v
    n = subdivisions
    ij = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    bary = np.array([(i / n, j / n, 1 - (i + j) / n) for i, j in ij])  # (S, 3)
    tri = v[mesh.triangles]  # (T, 3, 3)
    points = np.einsum('sk,tkd->tsd', bary, tri).reshape(-1, 3)
    return np.concatenate((v, points))


def score_map(mesh: SurfaceMesh, reference: SurfaceMesh) -> dict[str, float]:
    """``map_accuracy_median_m``, ``map_accuracy_mean_m``, ``map_completeness_5cm``,
    ``map_completeness_10cm`` (and the point counts) of ``mesh`` against ``reference``."""
    nan = float('nan')
    out = {
        'map_accuracy_median_m': nan,
        'map_accuracy_mean_m': nan,
        'map_completeness_5cm': 0.0,
        'map_completeness_10cm': 0.0,
        'map_points': float(len(mesh.vertices)),
        'map_reference_points': float(len(reference.vertices)),
    }
    if reference.is_empty:
        raise ValueError('the reference map is empty: nothing to score against')
    if mesh.is_empty:
        return out
    ref = surface_samples(reference)
    accuracy, _ = cKDTree(ref).query(mesh.vertices.astype(np.float64), workers=1)
    completeness, _ = cKDTree(surface_samples(mesh)).query(reference.vertices.astype(np.float64), workers=1)
    out['map_accuracy_median_m'] = float(np.median(accuracy))
    out['map_accuracy_mean_m'] = float(np.mean(accuracy))
    out['map_completeness_5cm'] = float(np.mean(completeness <= 0.05))
    out['map_completeness_10cm'] = float(np.mean(completeness <= 0.10))
    return out
