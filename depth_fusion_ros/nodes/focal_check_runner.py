"""``multi_view_node``'s focal length check, off the callback thread (``multiview/focal_check.py``).

The callbacks offer every posed frame; only the frames the check wants as its next sample
(a pose comparison, microseconds) are queued, and a daemon thread computes their features
and, once, the estimate. A full queue drops the offered frame (the next one that moved far
enough is taken instead): the check never holds up the stream.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable
from typing import Any

from ..camera import PinholeCamera
from ..data.sequence import Frame
from ..multiview.focal_check import FOCAL_CHECK_MODES, FocalCheck, FocalCheckConfig, FocalEstimate
from .params import ParamSpec, build_dataclass, dataclass_specs

FOCAL_CHECK_LIMITS: dict[str, Any] = {
    'mode': FOCAL_CHECK_MODES,
    'min_baseline': (1e-4, None),
    'min_rotation_deg': (1e-3, 180.0),
    'pairs': (5, 10000),
    'threshold': (1e-3, 0.9),
    'max_stderr': (1e-5, 1.0),
    'min_matches': (8, 100000),
    'features': (50, 100000),
}

FOCAL_CHECK_PARAMETERS: tuple[ParamSpec, ...] = tuple(
    dataclass_specs(FocalCheckConfig, 'focal_check', {}, FOCAL_CHECK_LIMITS)
)


class FocalCheckRunner:
    """Feeds a :class:`FocalCheck` from the callbacks on its own thread; reports the result once."""

    def __init__(
        self, config: FocalCheckConfig, on_result: Callable[[PinholeCamera, FocalEstimate], None]
    ) -> None:
        self.config = config
        self._on_result = on_result
        self._check: FocalCheck | None = None
        self._queue: queue.Queue[tuple[Any, Any] | None] = queue.Queue(maxsize=2)
        self._thread: threading.Thread | None = None
        #: ``(estimate, corrected camera)``: made once per estimate, not per frame.
        self._corrected: tuple[FocalEstimate, PinholeCamera] | None = None

    @classmethod
    def from_parameters(
        cls, params: dict[str, Any], on_result: Callable[[PinholeCamera, FocalEstimate], None]
    ) -> FocalCheckRunner:
        return cls(build_dataclass(FocalCheckConfig, params, 'focal_check'), on_result)

    @property
    def camera(self) -> PinholeCamera | None:
        """The camera being checked (``None`` before the first frame)."""
        return None if self._check is None else self._check.camera

    @property
    def result(self) -> FocalEstimate | None:
        """The current camera's estimate, once the check has it."""
        return None if self._check is None else self._check.result

    def camera_for(self, camera: PinholeCamera) -> PinholeCamera:
        """The camera the multi-view depth uses for frames of ``camera``: the fitted focal length
        once the check disagreed with this camera and ``focal_check.mode`` is correct, else
        ``camera`` itself."""
        result = self.result
        if self.config.mode != 'correct' or result is None or result.verdict != 'disagrees':
            return camera
        if camera != self.camera:
            return camera
        if self._corrected is None or self._corrected[0] is not result:
            self._corrected = (result, result.corrected(camera))
        return self._corrected[1]

    def status(self) -> str:
        """One phrase for the diagnostics."""
        if self.config.mode == 'off':
            return 'off'
        if self.result is not None:
            return f'{self.result.verdict}: fx {self.result.told_fx:.1f} -> {self.result.fx:.1f} px'
        pairs = 0 if self._check is None else len(self._check.pairs)
        return f'collecting ({pairs} of {self.config.pairs} image pairs)'

    def offer(self, frame: Frame, camera: PinholeCamera) -> None:
        """A posed frame on the working grid (callback thread): queued when the check wants it
        (its grey image is made only then)."""
        if self.config.mode == 'off':
            return
        if self._check is None or self._check.camera != camera:  # a new camera: check it anew
            self._stop()
            self._check = FocalCheck(camera, self.config)
            self._queue = queue.Queue(maxsize=2)
            self._thread = threading.Thread(target=self._run, args=(self._check, self._queue), daemon=True)
            self._thread.name = 'focal_check'
            self._thread.start()
        if not self._check.wants(frame.pose):  # also once it has its estimate
            return
        with contextlib.suppress(queue.Full):  # busy: a later frame that moved as far is taken instead
            self._queue.put_nowait((frame.gray, frame.pose))

    def close(self) -> None:
        self._stop()

    def _stop(self) -> None:
        if self._thread is not None:
            with contextlib.suppress(queue.Full):  # full: it stops at its next item (not its check)
                self._queue.put_nowait(None)
            self._thread = None

    def _run(self, check: FocalCheck, inbox: queue.Queue) -> None:
        while True:
            item = inbox.get()
            if item is None or check is not self._check:
                return
            estimate = check.add(*item)
            if estimate is not None:
                self._on_result(check.camera, estimate)
                return
