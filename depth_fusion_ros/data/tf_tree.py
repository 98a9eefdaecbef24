"""A ROS 1 bag's ``/tf`` tree, looked up (interpolated) at given stamps.

The converter needs camera-to-world poses at the colour stamps when a bag's only pose source
is a chain of transforms; composing a chain needs every edge at common stamps, hence lookups
at query stamps rather than the edges' own samples.
"""

from __future__ import annotations

import numpy as np

from .tum import TumTrajectory


def frame_name(name: str) -> str:
    """tf frame names without ROS 1's leading slash."""
    return name.lstrip('/')


class TfTree:
    """Transforms from ``/tf`` and ``/tf_static``, looked up (interpolated) at given stamps.

    Each child frame has one parent (a tf tree). An edge that only ever published one value,
    came from ``/tf_static``, or never changed is constant; others are interpolated (linear
    translation, slerp) and invalid outside the span they were published for.
    """

    def __init__(self) -> None:
        self._edges: dict[str, tuple[str, list[int], list[np.ndarray], bool]] = {}

    def add(
        self, parent: str, child: str, stamp_ns: int, T_parent_child: np.ndarray, static: bool = False
    ) -> None:
        parent, child = frame_name(parent), frame_name(child)
        edge = self._edges.setdefault(child, (parent, [], [], static))
        if edge[0] != parent:
            raise ValueError(f'tf frame {child!r} has two parents: {edge[0]!r} and {parent!r}')
        edge[1].append(int(stamp_ns))
        edge[2].append(T_parent_child)

    @property
    def frames(self) -> set[str]:
        return set(self._edges) | {e[0] for e in self._edges.values()}

    def _edge_at(self, child: str, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        _, stamps, poses, static = self._edges[child]
        arr = np.asarray(poses, dtype=np.float64)
        if static or len(arr) == 1 or np.allclose(arr, arr[0], rtol=0.0, atol=1e-12):
            return np.broadcast_to(arr[-1], (len(query_ns), 4, 4)), np.ones(len(query_ns), bool)
        return TumTrajectory.from_samples('/tf', stamps, arr).interpolate(query_ns)

    def lookup(self, target: str, source: str, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``T_target_source`` at each stamp, and whether it is known there.

        ``target`` must be an ancestor of ``source`` (e.g. ``world`` -> ... -> camera).
        """
        target, source = frame_name(target), frame_name(source)
        query_ns = np.asarray(query_ns, dtype=np.int64)
        T = np.tile(np.eye(4), (len(query_ns), 1, 1))
        valid = np.ones(len(query_ns), bool)
        frame, seen = source, set()
        while frame != target:
            if frame not in self._edges or frame in seen:
                known = ', '.join(sorted(self.frames)) or 'none'
                raise ValueError(f'no /tf chain from {target!r} to {source!r} (frames: {known})')
            seen.add(frame)
            T_edge, ok = self._edge_at(frame, query_ns)
            T = np.einsum('nij,njk->nik', T_edge, T)
            valid &= ok
            frame = self._edges[frame][0]
        T[~valid] = np.nan
        return T, valid
