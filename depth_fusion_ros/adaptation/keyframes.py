"""Assembles a keyframe's training signals as the graph publishes them, part by part.

In the node graph a keyframe's image, pose, multi-view depth and score arrive on separate
topics at different times, keyed by the same header stamp. ``KeyframeAssembler`` collects
them and returns an :class:`~.sample.AdaptSample` as soon as the image, depth and score are
in, with the pose, the depth's std and the fusion's verdict (``trust``, a ``FusionTrust``: the
reason the guard trusted none of its points, '' when it did, and the factor the fusion moved
them by; ``fusion_trust.py``) when they came first or are still expected. It keeps
the most recent posed keyframes as the photometric neighbours of the next ones (the previous
keyframes with enough baseline), and bounded memory: at most ``max_pending`` incomplete
keyframes.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..camera import PinholeCamera
from .fusion_trust import AS_IS
from .sample import AdaptSample, Neighbour, make_sample

PARTS = ('rgb', 'depth', 'score', 'pose', 'std', 'trust')
#: Parts a keyframe is complete without, until one of their kind has arrived.
OPTIONAL_PARTS = ('pose', 'std', 'trust')


@dataclass
class _Parts:
    values: dict[str, Any] = field(default_factory=dict)
    camera: PinholeCamera | None = None


class KeyframeAssembler:
    """Pairs image / pose / depth / score by stamp; yields samples, keeps posed neighbours."""

    def __init__(
        self,
        *,
        select_fraction: float = 0.25,
        holdout_fraction: float = 0.2,
        seed: int = 0,
        neighbours: int = 2,
        min_baseline: float = 0.02,
        max_pending: int = 8,
        window: int = 8,
        max_relative_std: float = 0.15,
    ):
        self.select_fraction = select_fraction
        self.holdout_fraction = holdout_fraction
        self.seed = seed
        self.n_neighbours = int(neighbours)
        self.min_baseline = float(min_baseline)
        self.max_pending = int(max_pending)
        self.max_relative_std = float(max_relative_std)
        self._pending: OrderedDict[int, _Parts] = OrderedDict()
        #: The recent posed keyframes, by stamp (ns): the neighbours of the next ones.
        self._recent: deque[tuple[int, Neighbour]] = deque(maxlen=max(1, window))
        #: The optional parts (pose, std, trust) that have arrived once: from then on a keyframe
        #: waits for its own (until it is evicted); a graph publishes each for every keyframe or
        #: never.
        self.optional_seen: set[str] = set()
        self.evicted_incomplete = 0
        #: The last keyframes given as samples: an optional part that comes after its keyframe
        #: was given (the first fusion verdict, which comes after the other parts) is let go
        #: instead of waiting as a keyframe that never completes.
        self._given: deque[int] = deque(maxlen=64)

    def add(
        self, stamp_ns: int, part: str, value: Any, camera: PinholeCamera | None = None
    ) -> list[AdaptSample]:
        """Add one part; returns the samples that became complete (usually none or one)."""
        if part not in PARTS:
            raise ValueError(f'unknown keyframe part {part!r}')
        if part in OPTIONAL_PARTS:
            self.optional_seen.add(part)
            if int(stamp_ns) in self._given and int(stamp_ns) not in self._pending:
                return []
        entry = self._pending.setdefault(int(stamp_ns), _Parts())
        entry.values[part] = value
        if camera is not None:
            entry.camera = camera
        out: list[AdaptSample] = []
        if self._ready(entry, waiting=True):
            out.append(self._finish(int(stamp_ns)))
        while len(self._pending) > self.max_pending:
            old_stamp, old = next(iter(self._pending.items()))
            if self._ready(old, waiting=False):
                out.append(self._finish(old_stamp))  # its pose (or std) never came: without it
            else:
                self._pending.pop(old_stamp)
                self.evicted_incomplete += 1
        return out

    def repose(self, turn: np.ndarray) -> int:
        """The camera was turned (a mount check's correction, which holds for the whole run):
        the neighbours kept and the poses waiting are re-posed, ``T @ turn``, so the
        photometric pairs of the keyframes to come compare poses of one camera. Returns how
        many poses moved. (The samples already made keep their own, consistent among
        themselves.)"""
        return len(self._move(lambda stamp, T: T @ turn))

    def reread(self, poses: dict[int, np.ndarray]) -> set[int]:
        """multi_view_node read these keyframes' poses again (by stamp, ns: a corrected time
        offset, nodes/posing.py): the neighbours kept and the poses waiting take them, so the
        photometric pairs of the keyframes to come compare poses read at one offset. Returns
        the stamps it held (the others have not come yet, or are gone)."""
        return self._move(lambda stamp, T: poses.get(stamp))

    def _move(self, pose_of: Callable[[int, np.ndarray], np.ndarray | None]) -> set[int]:
        """Give the neighbours kept and the poses waiting ``pose_of(stamp, pose)`` where it is
        not None; returns their stamps."""
        moved = set()
        for stamp, n in self._recent:
            T = pose_of(stamp, n.pose)
            if T is not None:
                n.pose = T
                moved.add(stamp)
        for stamp, entry in self._pending.items():
            T = pose_of(stamp, entry.values['pose']) if 'pose' in entry.values else None
            if T is not None:
                entry.values['pose'] = T
                moved.add(stamp)
        return moved

    def _ready(self, entry: _Parts, waiting: bool) -> bool:
        v = entry.values
        if not all(k in v for k in ('rgb', 'depth', 'score')) or entry.camera is None:
            return False
        return not waiting or self.optional_seen.issubset(v)

    def _neighbours(self, pose: np.ndarray) -> list[Neighbour]:
        chosen = []
        for _, n in reversed(self._recent):
            if np.linalg.norm(n.pose[:3, 3] - pose[:3, 3]) >= self.min_baseline:
                chosen.append(n)
            if len(chosen) >= self.n_neighbours:
                break
        return chosen

    def _finish(self, stamp_ns: int) -> AdaptSample:
        entry = self._pending.pop(stamp_ns)
        self._given.append(stamp_ns)
        v = entry.values
        trust = v.get('trust', AS_IS)
        pose = v.get('pose')
        neighbours = self._neighbours(pose) if pose is not None and self.n_neighbours > 0 else []
        sample = make_sample(
            stamp_ns,
            v['rgb'],
            entry.camera,
            v['depth'],
            v['score'],
            select_fraction=self.select_fraction,
            holdout_fraction=self.holdout_fraction,
            seed=self.seed,
            pose=pose,
            neighbours=neighbours,
            mv_std=v.get('std'),
            max_relative_std=self.max_relative_std,
            untrusted=trust.untrusted,
            points_scale=trust.points_scale,
        )
        if pose is not None:
            self._recent.append((stamp_ns, Neighbour(v['rgb'], pose)))
        return sample
