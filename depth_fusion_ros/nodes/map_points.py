"""map_node's published surface (``depth_fusion/map/points``), extracted without stalling the map.

Extracting the surface costs about 0.15 ms per voxel block on 2 CPU cores (surface nets on
the blocks, mapping/block_surface.py: 0.07 s at 588 blocks, 1.0 s at 6601;
``scripts/diag/map_extraction.py``), so at the default cap of 10000 blocks one extraction
takes more than a second. Done on the executor thread holding the map's lock at
``points_rate`` (1 Hz), it held the lock most of the time and integration waited behind it.
So the blocks are copied under the lock (a memory copy) and the surface is extracted and
published from a thread of its own; and a publication starts only when the last one's cost,
spread over the time since it began, stays within ``MAX_SHARE`` of a core: a large map is
published less often (``points_throttled`` is noted with the period it gets), never at the
cost of integration. A map larger than ``map.max_blocks`` publishes its archived blocks too:
their surface is extracted once per block, up to :data:`ARCHIVED_PER_PUBLICATION` blocks a
publication (their voxels read under the lock, the surface outside it), and kept as points
(mapping/archived_surface.py).
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from ..data import messages
from ..mapping.archived_surface import ArchivedSurface, resident_surface
from ..mapping.block_surface import block_mesh
from ..mapping.surface import SurfaceMesh

if TYPE_CHECKING:
    from .map_node import MapNode

#: Most of one core the published surface may take (the extraction time over the period).
MAX_SHARE = 0.25
#: Archived blocks whose surface one publication extracts (read under the map's lock: ~10 KB
#: each at 8^3 voxels; extracted outside it, ~0.15 ms each); the rest follow in later ones.
ARCHIVED_PER_PUBLICATION = 2000


class MapPointsPublisher:
    """Publishes the map surface as a PointCloud2 from its own thread, duty-cycle limited."""

    def __init__(self, node: MapNode, publisher: Any, rate: float, points_max: int) -> None:
        self.node = node
        self.publisher = publisher
        self.period = 1.0 / rate if rate > 0 else float('inf')
        self.points_max = points_max
        #: The surface points of the map's archived blocks (only this class's thread uses it).
        self.archived = ArchivedSurface(points_max)
        self.last_seconds = 0.0
        self._next = 0.0
        self._thread: threading.Thread | None = None

    def tick(self) -> None:
        """Timer callback: start a publication when the map changed and the budget allows."""
        node = self.node
        if not node._dirty or (self._thread is not None and self._thread.is_alive()):
            return
        if time.monotonic() < self._next:
            return
        node._dirty = False
        self._thread = threading.Thread(target=self._run, name='map_points', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        node = self.node
        t0 = time.monotonic()
        try:
            mesh, frame = self._surface()
            self._publish(mesh, frame)
        except Exception as exc:  # a failed publication leaves the map as it is
            node.stats.dropped('points_failed', f'map surface not published: {type(exc).__name__}: {exc}')
            return
        finally:
            self.last_seconds = time.monotonic() - t0
            gap = self.last_seconds * (1.0 / MAX_SHARE - 1.0)
            self._next = time.monotonic() + gap
        if self.last_seconds + gap > self.period * 1.05:
            node.stats.noted(
                'points_throttled',
                f'the map surface took {self.last_seconds:.2f} s to extract ({node.map.n_blocks} blocks): '
                f'published every {self.last_seconds + gap:.1f} s instead of {self.period:g} s, so that it '
                f'takes at most {MAX_SHARE:.0%} of a core',
            )

    def _surface(self) -> tuple[SurfaceMesh, str]:
        """The blocks copied under the lock, the surface extracted outside it (an engine
        without a block copy, Open3D's, is extracted under the lock), with the points of the
        archived blocks."""
        node = self.node
        with node._lock:
            frame = node._world_frame or 'world'
            blocks = getattr(node.map.engine, 'blocks', None)
            if blocks is None:
                return node.map.mesh(), frame
            snapshot = blocks().clone()
            archive = getattr(node.map.engine, 'archive', None)
            versions = archive.versions() if archive is not None else {}
            read = archive.read if archive is not None else None
            pending = self.archived.plan(archive, versions, read, snapshot, ARCHIVED_PER_PUBLICATION)
        if pending is None:  # nothing archived
            return block_mesh(snapshot, triangles=False), frame  # the cloud is the vertices
        mesh = resident_surface(snapshot, pending)
        self.archived.extract(pending, snapshot)
        if not self.archived.blocks:
            return mesh, frame
        points, colours = self.archived.cloud()
        vertices, colours = np.concatenate((mesh.vertices, points)), np.concatenate((mesh.colours, colours))
        return SurfaceMesh(vertices, np.zeros((0, 3), np.int64), colours), frame

    def _publish(self, mesh: SurfaceMesh, frame: str) -> None:
        points, colours = mesh.vertices, mesh.colours
        if len(points) > self.points_max:
            keep = np.linspace(0, len(points) - 1, self.points_max).astype(np.int64)
            points, colours = points[keep], colours[keep]
        node = self.node
        header = messages.header_msg(node.get_clock().now().nanoseconds, frame, kind=messages.RCLPY)
        self.publisher.publish(messages.pointcloud2_msg(points, header, kind=messages.RCLPY, rgb=colours))
        node.stats.published('points')

    def wait(self, timeout: float) -> None:
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
