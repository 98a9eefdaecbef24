"""``multi_view_node``'s time offset check, off the callback thread (``multiview/time_offset_check.py``).

The check reads poses at other times than the images' stamps, so it needs every posed frame's
stamp and pose (queued as they come, tiny), and the grey image of the frames it wants as
samples (:mod:`.check_runner`). Once it disagrees and ``time_offset_check.mode`` is correct,
the node reads the poses at the fitted offset (:attr:`TimeOffsetCheckRunner.correction`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..camera import PinholeCamera
from ..data.sequence import Frame
from ..multiview.time_offset_check import (
    TIME_OFFSET_CHECK_MODES,
    TimeOffsetCheck,
    TimeOffsetCheckConfig,
    TimeOffsetEstimate,
)
from .check_runner import CheckRunner
from .params import ParamSpec, build_dataclass, dataclass_specs

TIME_OFFSET_CHECK_LIMITS: dict[str, Any] = {
    'mode': TIME_OFFSET_CHECK_MODES,
    'max_offset': (0.002, 1.0),
    'min_baseline': (1e-4, None),
    'min_rotation_deg': (1e-3, 180.0),
    'pairs': (5, 10000),
    'early_pairs': (0, 10000),
    'threshold': (1e-4, 0.5),
    'max_stderr': (1e-5, 1.0),
    'min_matches': (8, 100000),
    'features': (50, 100000),
}

TIME_OFFSET_CHECK_PARAMETERS: tuple[ParamSpec, ...] = tuple(
    dataclass_specs(TimeOffsetCheckConfig, 'time_offset_check', {}, TIME_OFFSET_CHECK_LIMITS)
)


class TimeOffsetCheckRunner(CheckRunner):
    """Feeds a :class:`TimeOffsetCheck` from the callbacks on its own thread; reports once.

    A frame's grey image is made when the check wants the frame as its next sample, counted
    from the last frame queued with one (as :class:`.check_runner.PairedCheckRunner` does): a
    thread still busy with one sample is not handed grey images of the very next frames, which
    it would not use.
    """

    name = 'time_offset_check'
    #: Every frame's pose is queued (a sample's grey image too): a second of a 30 Hz stream.
    queue_size = 32

    def __init__(
        self,
        config: TimeOffsetCheckConfig,
        told: float,
        on_result: Callable[[PinholeCamera, TimeOffsetEstimate], None],
    ) -> None:
        super().__init__(config, on_result)
        self.told = told

    @classmethod
    def from_parameters(
        cls, params: dict[str, Any], on_result: Callable[[PinholeCamera, TimeOffsetEstimate], None]
    ) -> TimeOffsetCheckRunner:
        config = build_dataclass(TimeOffsetCheckConfig, params, 'time_offset_check')
        return cls(config, float(params['pose_time_offset']), on_result)

    @property
    def correction(self) -> float:
        """Seconds to add to ``pose_time_offset``: the fitted offset once the check disagreed and
        ``time_offset_check.mode`` is correct, else 0."""
        result = self.result
        if self.config.mode != 'correct' or result is None or result.verdict != 'disagrees':
            return 0.0
        return result.offset

    def _recipe(self, camera: PinholeCamera) -> tuple[type, tuple]:
        return TimeOffsetCheck, (camera, self.config, self.told)

    def _item(self, check: TimeOffsetCheck, frame: Frame) -> tuple[Any, float, Any]:
        # The check in the checks' process counts its pairs; the mirror here does not.
        wanted = self.collected < self.config.pairs and check.wants(
            frame.stamp, frame.pose, self._sample_pose
        )
        return (frame.gray if wanted else None), frame.stamp, frame.pose  # the grey image only then

    def _sample_pose_of(self, item: tuple[Any, float, Any]) -> Any:
        return item[2] if item[0] is not None else None  # a sample is an item with its grey image

    def _call(self, item: tuple[Any, float, Any]) -> tuple[str, tuple]:
        gray, stamp, pose = item
        return ('observe', (stamp, pose)) if gray is None else ('add', item)

    def status(self) -> str:
        """One phrase for the diagnostics."""
        if self.config.mode == 'off':
            return 'off'
        if self.result is not None:
            r = self.result
            if r.verdict == 'unobservable':  # no fit worth naming: the told offset stays
                return f'{r.verdict}: {r.fit_phrase()} (pose_time_offset {r.told:.3f} kept)'
            return f'{r.verdict}: {r.fit_phrase()} (pose_time_offset {r.fitted:.3f})'
        return f'collecting ({self.collected} of {self.config.pairs} image pairs)'
