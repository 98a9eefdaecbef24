"""The published cloud of a bounded map holds its archived blocks too (core, no ROS): the
surface of each archived block is extracted once, with its neighbours, and is the whole map's
surface there; blocks that come back leave it, blocks written again are extracted again."""

from __future__ import annotations

import numpy as np
import pytest
from test_block_archive import THERE_AND_BACK, _config, _slide

from depth_fusion_ros.mapping.archived_surface import ArchivedSurface, resident_surface
from depth_fusion_ros.mapping.block_surface import block_mesh

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _publish(surface: ArchivedSurface, tsdf, limit: int = 10_000) -> np.ndarray:
    """What map_points does: plan under the lock, extract outside; the cloud's points."""
    snapshot = tsdf.blocks().clone()
    pending = surface.plan(tsdf.archive, tsdf.archive.versions(), tsdf.archive.read, snapshot, limit)
    if pending is not None:
        surface.extract(pending, snapshot)
    resident = resident_surface(snapshot, pending).vertices
    return np.concatenate((resident, surface.cloud()[0]))


def _rows(points: np.ndarray) -> set[tuple[float, float, float]]:
    return {tuple(p) for p in np.round(points.astype(np.float64), 5)}


def test_the_cloud_of_a_bounded_map_is_the_whole_maps_surface(tmp_path):
    """Half way along a 6 m wall with 100 blocks in memory: the blocks behind the camera are
    archived. Before, the cloud was the blocks in memory alone; now every archived block's
    points are the whole map's mesh vertices in its cells, and the cloud is the whole mesh's
    vertices (the blocks in memory completed by their archived neighbours: no seam)."""
    tsdf = _slide(_config(tmp_path, max_blocks=100), THERE_AND_BACK[:9])
    assert tsdf.archived_blocks > 50
    whole = _rows(tsdf.mesh().vertices)
    surface = ArchivedSurface(max_points=1_000_000)
    cloud = _publish(surface, tsdf, limit=40)  # a part of the archive a publication
    assert len(surface.blocks) == 40
    cloud = _publish(surface, tsdf)
    assert len(surface.blocks) == tsdf.archived_blocks and surface.thinned == 0
    archived = _rows(surface.cloud()[0])
    assert archived <= whole and len(archived) == surface.points  # exactly the mesh's vertices there
    resident_only = _rows(block_mesh(tsdf.blocks(), triangles=False).vertices)
    covered = _rows(cloud)
    assert len(resident_only) < 0.6 * len(whole)  # the cloud before: the blocks in memory alone
    assert covered == whole and len(cloud) == len(whole)
    # Back along the wall: the blocks that come back leave the archived points; the rest stay.
    for x in THERE_AND_BACK[9:]:
        T = np.eye(4)
        T[0, 3] = x
        tsdf.integrate(np.full((120, 160), 1.5, np.float32), T, _camera())
    back = _publish(surface, tsdf)
    assert set(surface.blocks) == set(tsdf.archive.versions())
    assert _rows(surface.cloud()[0]) <= _rows(tsdf.mesh().vertices)
    assert _rows(back) == _rows(tsdf.mesh().vertices)


def test_the_archived_points_stay_within_their_cap_and_another_archive_starts_over(tmp_path):
    tsdf = _slide(_config(tmp_path, max_blocks=100), THERE_AND_BACK[:9])
    full = ArchivedSurface(max_points=1_000_000)
    _publish(full, tsdf)
    capped = ArchivedSurface(max_points=full.points // 3)
    _publish(capped, tsdf)
    assert capped.thinned == 2 and capped.points <= full.points // 3 and capped.points > full.points // 5
    other = _slide(_config(tmp_path, max_blocks=100), THERE_AND_BACK[:5])
    _publish(capped, other)
    assert capped.source is other.archive and set(capped.blocks) == set(other.archive.versions())


def _camera():
    from test_block_archive import CAMERA

    return CAMERA
