"""The ``multi_view_node``'s temporal depth filter (``multi_view.method: filter``).

The sweep needs only the keyframe and its neighbours; the filter must see every posed
frame, in order. The node's callbacks stay light: every posed frame is appended to a
bounded queue here, and the worker, when it takes a keyframe, first feeds the filter every
frame queued up to and including that keyframe, then asks for the keyframe's estimate. A
keyframe dropped from the worker queue (latest-wins) loses no frame: its frames stay queued
for the next keyframe. Frames beyond ``filter.max_queued_frames`` (a worker far behind) are
dropped oldest first and counted.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from ..camera import PinholeCamera
from ..data.sequence import Frame
from ..multiview.filter import DepthFilter
from ..multiview.filter_config import MULTI_VIEW_METHODS, FilterConfig
from ..multiview.filter_result import FilterResult
from ..multiview.semidense import MultiViewConfig
from .params import ParamSpec, build_dataclass, dataclass_specs

#: ``filter.*`` limits (the descriptions come from the ``#:`` comments of ``FilterConfig``).
FILTER_LIMITS: dict[str, Any] = {
    'max_candidate_fraction': (0.0, 1.0),
    'min_gradient': (0.0, 1.0),
    'min_epipolar_gradient': (0.0, 1.0),
    'pixel_sigma': (1e-3, 100.0),
    'pose_sigma': (0.0, 10.0),
    'min_information': (0.0, None),
    'search_sigmas': (0.1, 10.0),
    'min_search_px': (0.1, 100.0),
    'short_samples': (3, 256),
    'long_samples': (3, 4096),
    'max_step_px': (0.05, 100.0),
    'verify_samples': (0, 256),
    'medium_samples': (0, 4096),
    'seed_radius': (0, 50),
    'refine_samples': (1, 64),
    'seed_parallax': (0.0, None),
    'seed_attempts': (1, 1000),
    'max_cost': (0.0, 2.0),
    'min_distinctiveness': (0.0, 1.0),
    'init_a': (1e-3, None),
    'init_b': (1e-3, None),
    'min_inlier_ratio': (0.0, 1.0),
    'publish_inlier_ratio': (0.0, 1.0),
    'min_updates': (1, 100000),
    'score_relative_power': (0.0, 10.0),
    'max_relative_sigma': (1e-6, None),
    'min_parallax': (0.0, None),
    'max_rotation_deg': (0.0, 180.0),
    'keyframe_parallax': (0.0, None),
    'keyframe_rotation_deg': (0.0, 180.0),
    'keyframe_min_visible': (0.0, 1.0),
    'propagation_inflation': (1.0, None),
    'propagation_relative_sigma': (0.0, None),
    'fill_radius': (0, 50),
    'fill_min_neighbours': (1, 10000),
    'scene_depth': (1e-3, None),
}

FILTER_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'multi_view.method',
        'filter',
        'filter (default): a temporal Gaussian x uniform inverse-depth filter updated by every posed '
        "frame (filter.* parameters); sweep: the paper's per-keyframe inverse-depth sweep over the "
        'neighbours',
        choices=MULTI_VIEW_METHODS,
    ),
    ParamSpec(
        'filter.max_queued_frames',
        300,
        'filter: posed frames waiting for the worker at most (oldest dropped first, counted)',
        1,
        100000,
    ),
    *dataclass_specs(FilterConfig, 'filter', {}, FILTER_LIMITS),
)


class FilterFeed:
    """Posed frames queued by the callbacks, fed to a :class:`DepthFilter` by the worker."""

    def __init__(
        self,
        config: FilterConfig,
        matching: MultiViewConfig,
        device: str,
        max_queued: int,
        on_drop: Callable[[str], None],
    ) -> None:
        config.validate()
        self.config, self.matching, self.device = config, matching, device
        self._frames: deque[Frame] = deque()
        self._max_queued = int(max_queued)
        self._on_drop = on_drop
        self._lock = threading.Lock()
        self.filter: DepthFilter | None = None

    @classmethod
    def from_parameters(
        cls, params: dict[str, Any], matching: MultiViewConfig, device: str, on_drop: Callable[[str], None]
    ) -> FilterFeed | None:
        """The feed when ``multi_view.method`` is ``filter``, else ``None`` (the sweep)."""
        if params['multi_view.method'] != 'filter':
            return None
        config = build_dataclass(FilterConfig, params, 'filter')
        return cls(config, matching, device, int(params['filter.max_queued_frames']), on_drop)

    def append(self, frame: Frame) -> None:
        """Queue one posed frame (callback thread)."""
        with self._lock:
            self._frames.append(frame)
            while len(self._frames) > self._max_queued:
                old = self._frames.popleft()
                self._on_drop(f'filter frame {old.stamp:.3f} dropped: the worker is behind')

    def result_for(self, key: Frame, camera: PinholeCamera) -> FilterResult:
        """Feed every queued frame up to ``key`` (worker thread), then the estimate in ``key``."""
        if self.filter is None or self.filter.camera != camera:
            self.filter = DepthFilter(camera, self.config, self.matching, self.device)
        while True:
            with self._lock:
                if not self._frames or self._frames[0].index > key.index:
                    break
                frame = self._frames.popleft()
            self.filter.process(frame.gray, frame.pose)
        return self.filter.result(key.pose)
