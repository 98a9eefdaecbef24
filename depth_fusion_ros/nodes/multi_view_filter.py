"""The ``multi_view_node``'s temporal depth filter (``multi_view.method: filter``).

The sweep needs only the keyframe and its neighbours; the filter must see every posed
frame, in order. The node's callbacks stay light: every posed frame is appended to a
bounded queue here, and a feed thread gives each to the filter as soon as it can, so the
filter keeps up with the stream between keyframes. When the frame is a keyframe, the feed
reads the keyframe's estimate right after updating with it (what the filter knows then,
as before) and keeps it for the worker, which only waits for it: a keyframe's latency no
longer includes the updates of the frames since the last one (4 of 5 at the default
policy; 100-140 ms of the node's 160-190 ms per keyframe on 2 cores). A keyframe the worker
drops (latest-wins) loses no frame: the filter saw them all. Frames beyond
``filter.max_queued_frames`` (a feed far behind) are dropped oldest first and counted; a
keyframe among them fails its job (``processing_error``) instead of waiting. Before that, a
live stream that outruns the filter makes it skip frames: beyond ``filter.max_lag_frames``
waiting frames the oldest non-keyframes are skipped (counted as ``filter_skipped``), so the
keyframes still come out in time; a paced replay (``depth-fusion run``) sets 0, never skip.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, NamedTuple

from ..camera import PinholeCamera
from ..data.sequence import Frame
from ..multiview.filter import DepthFilter
from ..multiview.filter_config import MULTI_VIEW_METHODS, FilterConfig
from ..multiview.filter_result import FilterResult
from ..multiview.semidense import MultiViewConfig
from .filter_rate import UpdateRate
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
    'first_check_px': (0.0, 100.0),
    'first_check_distinctiveness': (0.0, 1.0),
    'max_cost': (0.0, 2.0),
    'min_distinctiveness': (0.0, 1.0),
    'init_a': (1e-3, None),
    'init_b': (1e-3, None),
    'min_inlier_ratio': (0.0, 1.0),
    'publish_inlier_ratio': (0.0, 1.0),
    'min_updates': (1, 100000),
    'first_keyframe_min_updates': (1, 100000),
    'score_relative_power': (0.0, 10.0),
    'max_relative_sigma': (1e-6, None),
    'min_published_fraction': (0.0, 1.0),
    'published_fraction_cells': (0, 1000),
    'min_parallax': (0.0, None),
    'max_rotation_deg': (0.0, 180.0),
    'keyframe_parallax': (0.0, None),
    'keyframe_rotation_deg': (0.0, 180.0),
    'keyframe_min_visible': (0.0, 1.0),
    'propagation_inflation': (1.0, None),
    'propagation_relative_sigma': (0.0, None),
    'fill_radius': (0, 50),
    'fill_min_updates': (1, 1000),
    'fill_min_neighbours': (1, 10000),
    'scene_depth': (1e-3, None),
    'focal_uncertainty': (0.0, 1.0),
    'refine_sigma_deg': (1e-3, 45.0),
    'refine_sigma_m': (1e-5, 10.0),
    'refine_corners': (20, 10000),
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
        'filter: posed frames waiting for the filter at most (oldest dropped first, counted)',
        1,
        100000,
    ),
    ParamSpec(
        'filter.max_lag_frames',
        5,
        'filter: when more frames than this wait for the filter, the oldest ones that are not '
        'keyframes are skipped (counted, filter_skipped): with a live camera the filter keeps up by '
        'updating with fewer frames, and keyframes still come out in time; keyframes are never '
        'skipped. 0: never skip (depth-fusion run sets it for paced replays)',
        0,
        100000,
    ),
    ParamSpec(
        'filter.max_update_rate',
        10.0,
        'filter: Hz (stamp time) at which frames that are not keyframes update the filter at most while '
        'the machine is short of time (filter.rate_cap_load); the others are passed over before any work '
        '(counted in the diagnostics). On 2 cores with a live 30 Hz camera and a loaded machine the CPU '
        'then goes to the fusion sooner; 0: every frame always (paced replays set 0)',
        0.0,
        1000.0,
    ),
    ParamSpec(
        'filter.rate_cap_load',
        1.0,
        'filter: max_update_rate applies only while a filter update takes more than this share of the '
        'time between two frames (the filter cannot keep up: smoothed wall time against stamp time); '
        'below it every frame updates (live TUM fr1_xyz fused MAE 0.290 against 0.323 m). 0: the cap always',
        0.0,
        100.0,
    ),
    *dataclass_specs(FilterConfig, 'filter', {}, FILTER_LIMITS),
)


#: Keyframe estimates kept for the worker at most (a worker that dropped its jobs).
MAX_UNCLAIMED = 16
#: Seconds the worker waits for a keyframe's estimate before the job fails.
RESULT_TIMEOUT = 120.0


class _Queued(NamedTuple):
    """One posed frame waiting for the filter; ``token`` is handed to ``on_consumed`` once the
    feed is done with it."""

    frame: Frame
    camera: PinholeCamera
    keyframe: bool
    token: int | None


class FilterFeed:
    """Posed frames queued by the callbacks, fed to a :class:`DepthFilter` by its own thread;
    keyframe estimates handed to the worker.

    ``on_consumed(token)`` is called once for every frame appended with a token, when the feed is
    done with it (updated, passed over, skipped or dropped): the node's ``image_done`` event, so
    that a paced replay waits for the filter itself, not only for the callbacks that queue its
    frames (the queue would otherwise fill with the frames sent after a keyframe was fused, and
    the next keyframe would wait behind them: ``nodes/pacer.py``)."""

    def __init__(
        self,
        config: FilterConfig,
        matching: MultiViewConfig,
        device: str,
        max_queued: int,
        on_drop: Callable[[str], None],
        on_error: Callable[[str], None] | None = None,
        max_lag: int = 0,
        on_skip: Callable[[str], None] | None = None,
        max_rate: float = 0.0,
        on_consumed: Callable[[int], None] | None = None,
        rate_cap_load: float = 0.0,
    ) -> None:
        config.validate()
        self.config, self.matching, self.device = config, matching, device
        self._frames: deque[_Queued] = deque()
        self._on_consumed = on_consumed
        self._max_queued = int(max_queued)
        self._max_lag = int(max_lag)
        #: Which non-keyframes update (``max_update_rate`` while loaded: ``nodes/filter_rate.py``).
        self.rate = UpdateRate(max_rate, rate_cap_load)
        #: Frames passed over by ``max_update_rate`` (diagnostics).
        self.rate_skipped = 0
        #: ``FilterStats`` counts of the filters this feed replaced (restarts, a new camera):
        #: :attr:`jumps`, :attr:`refined_poses` and :attr:`kept_told_poses` add the current filter's.
        self._past_counts = {'jumps': 0, 'refined': 0, 'kept_told': 0}
        self._on_drop = on_drop
        self._on_error = on_error or on_drop
        self._on_skip = on_skip or on_drop
        self._cond = threading.Condition()
        #: Keyframe index -> its estimate, or the error that prevented it.
        self._results: dict[int, FilterResult | Exception] = {}
        self._discarded: set[int] = set()
        self._closed = False
        self._busy = False
        #: from this frame index on the filter starts over (a new stream), once
        self._restart_at: int | None = None
        self.filter: DepthFilter | None = None
        #: Frames the filter has been given (the feed thread's progress).
        self.fed = 0
        #: The focal length uncertainty a keyframe's estimate is published with
        #: (``DepthFilter.focal_uncertainty``): the node hands in its focal check's
        #: (``FocalCheckRunner.uncertainty``); read at each keyframe.
        self.focal_uncertainty: Callable[[], float] = lambda: config.focal_uncertainty
        self._thread = threading.Thread(target=self._run, name='filter_feed', daemon=True)
        self._thread.start()

    @classmethod
    def from_parameters(
        cls,
        params: dict[str, Any],
        matching: MultiViewConfig,
        device: str,
        on_drop: Callable[[str], None],
        on_error: Callable[[str], None] | None = None,
        on_skip: Callable[[str], None] | None = None,
        on_consumed: Callable[[int], None] | None = None,
    ) -> FilterFeed | None:
        """The feed when ``multi_view.method`` is ``filter``, else ``None`` (the sweep)."""
        if params['multi_view.method'] != 'filter':
            return None
        config = build_dataclass(FilterConfig, params, 'filter')
        queued, lag = int(params['filter.max_queued_frames']), int(params['filter.max_lag_frames'])
        rate = float(params['filter.max_update_rate'])
        load = float(params['filter.rate_cap_load'])
        return cls(config, matching, device, queued, on_drop, on_error, lag, on_skip, rate, on_consumed, load)

    def append(
        self, frame: Frame, camera: PinholeCamera, keyframe: bool = False, token: int | None = None
    ) -> None:
        """Queue one posed frame (callback thread); ``keyframe``: the worker will ask for its
        estimate; ``token``: handed to ``on_consumed`` when the feed is done with the frame."""
        done: list[int | None] = []
        with self._cond:
            self.rate.seen(frame.stamp)  # every frame of the stream, skipped ones too
            self._frames.append(_Queued(frame, camera, keyframe, token))
            if self._max_lag > 0 and len(self._frames) > self._max_lag:
                done += self._skip_behind()
            while len(self._frames) > self._max_queued:
                old = self._frames.popleft()
                message = f'filter frame {old.frame.stamp:.3f} dropped: the filter is behind'
                if old.keyframe:
                    self._keep(old.frame.index, RuntimeError(message))
                self._on_drop(message)
                done.append(old.token)
            self._cond.notify_all()
        self._consumed(*done)

    def _consumed(self, *tokens: int | None) -> None:
        """Tell ``on_consumed`` the feed is done with these frames (no lock held: it publishes)."""
        if self._on_consumed is None:
            return
        for token in tokens:
            if token is not None:
                self._on_consumed(token)

    def restart(self, first_index: int) -> None:
        """A new stream begins at frame ``first_index``: the filter starts over there (callback
        thread). The frames before it, queued or not, still update the previous keyframe."""
        with self._cond:
            self._restart_at = int(first_index)

    def _skip_behind(self) -> list[int | None]:
        """Skip the oldest non-keyframes until at most ``max_lag`` frames wait (lock held); their
        tokens."""
        excess = len(self._frames) - self._max_lag
        kept: deque[_Queued] = deque()
        skipped: list[_Queued] = []
        for item in self._frames:
            if excess > 0 and not item.keyframe:
                skipped.append(item)
                excess -= 1
            else:
                kept.append(item)
        self._frames = kept
        for item in skipped:
            self._on_skip(f'filter frame {item.frame.stamp:.3f} skipped: the filter is behind a live stream')
        return [item.token for item in skipped]

    def result_for(self, key: Frame, camera: PinholeCamera) -> FilterResult:
        """The estimate in keyframe ``key`` once the filter has seen it (worker thread)."""
        del camera  # the feed built the filter for the camera each frame came with
        with self._cond:
            ready = self._cond.wait_for(lambda: key.index in self._results or self._closed, RESULT_TIMEOUT)
            outcome = self._results.pop(key.index, None)
        if isinstance(outcome, Exception):
            raise outcome
        if outcome is None:
            why = 'the node is shutting down' if ready else f'not ready after {RESULT_TIMEOUT:g} s'
            raise RuntimeError(f'filter estimate of keyframe {key.stamp:.3f}: {why}')
        return outcome

    def discard(self, index: int) -> None:
        """The worker dropped keyframe ``index``: its estimate is not wanted (now or later)."""
        with self._cond:
            if self._results.pop(index, None) is None:
                self._discarded.add(index)
                while len(self._discarded) > MAX_UNCLAIMED:  # lost before the filter got there
                    self._discarded.discard(min(self._discarded))

    def close(self, timeout: float = 5.0) -> None:
        """Stop the feed thread (after the frame it is on); waiting workers fail at once."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def idle(self) -> bool:
        """Nothing queued or in hand: the filter has seen every frame appended so far (tests;
        the calibration checks wait for it, nodes/check_runner.py)."""
        with self._cond:
            return not self._frames and not self._busy

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._frames or self._closed)
                if self._closed:
                    return
                frame, camera, keyframe, token = self._frames.popleft()
                if self._restart_at is not None and frame.index >= self._restart_at:
                    self._retire_filter()
                    self._restart_at = None  # built again below
                    self.rate.reset()
                skip = not keyframe and self.rate.too_soon(frame.stamp)
                if skip:
                    self.rate_skipped += 1
                else:
                    self._busy = True
            if skip:
                self._consumed(token)
                continue
            outcome: FilterResult | Exception | None = None
            started = time.perf_counter()
            try:
                if self.filter is None or (self.filter.camera != camera and not self.filter.refocus(camera)):
                    self._retire_filter()
                    self.filter = DepthFilter(camera, self.config, self.matching, self.device)
                self.filter.process(frame.gray, frame.pose)
                self.fed += 1
                if keyframe:
                    self.filter.focal_uncertainty = self.focal_uncertainty()
                    outcome = self.filter.result(frame.pose)
            except Exception as exc:  # one bad frame must not end the feed
                outcome = exc
                if not keyframe:
                    self._on_error(f'filter frame {frame.stamp:.3f} failed: {type(exc).__name__}: {exc}')
            with self._cond:
                # A failed update counts too (as the cap did before): its time was spent.
                self.rate.updated(frame.stamp, time.perf_counter() - started)
                if keyframe and outcome is not None:
                    self._keep(frame.index, outcome)
                self._busy = False
                self._cond.notify_all()
            self._consumed(token)

    @property
    def jumps(self) -> int:
        """Filter keyframes switched across a jump (turned more than ``filter.max_rotation_deg``:
        the carried estimates confirmed again before they are published), over the feed's life."""
        return self._lifetime('jumps')

    @property
    def refined_poses(self) -> int:
        """Frames whose pose the filter refined against its keyframe's image, over the feed's life."""
        return self._lifetime('refined')

    @property
    def kept_told_poses(self) -> int:
        """Frames that kept their told pose because the refinement failed, over the feed's life."""
        return self._lifetime('kept_told')

    def _lifetime(self, name: str) -> int:
        """A ``FilterStats`` count over every filter this feed has built."""
        current = self.filter
        return self._past_counts[name] + (getattr(current.stats, name) if current is not None else 0)

    def _retire_filter(self) -> None:
        """Drop the filter (it is built again for the next frame), keeping its counts."""
        if self.filter is not None:
            for name in self._past_counts:
                self._past_counts[name] += getattr(self.filter.stats, name)
        self.filter = None

    def _keep(self, index: int, outcome: FilterResult | Exception) -> None:
        """Hold ``outcome`` for the worker (lock held), unless it was discarded; bounded."""
        if index in self._discarded:
            self._discarded.discard(index)
            return
        self._results[index] = outcome
        while len(self._results) > MAX_UNCLAIMED:
            self._results.pop(next(iter(self._results)))
