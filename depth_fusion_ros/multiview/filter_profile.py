"""Where a depth-filter frame spends its time: exclusive seconds per stage, when asked for.

The filter's cost per frame is the issue's target (at most 1/5 of a sweep per keyframe);
the bench (``bench.multi_view_filter``) prints this breakdown so a change can be aimed at
the stage that costs, on CPU and on CUDA alike. Stages switch at a handful of boundaries
per frame; each switch charges the time since the last one to the stage being left, so the
stages add up to the frame (nested work, e.g. the descriptors of a frame that becomes the
keyframe, is charged to itself, not twice). Off by default: a switch is then one attribute
test. CPU time of the process on CPU (a shared machine's load moves it less than the wall
clock); wall clock after a synchronisation on CUDA (asynchronous kernels have no CPU time).
"""

from __future__ import annotations

import time

import torch


class StageClock:
    """Exclusive seconds per stage name; ``switch`` to a stage, ``stop`` at the end of a frame."""

    def __init__(self, device: torch.device, enabled: bool = False) -> None:
        self.device = device
        self.enabled = enabled
        self.seconds: dict[str, float] = {}
        self._stage: str | None = None
        self._since = 0.0

    def _now(self) -> float:
        if self.device.type == 'cuda':
            torch.cuda.synchronize(self.device)
            return time.perf_counter()
        return time.process_time()

    def switch(self, stage: str | None) -> str | None:
        """Charge the time since the last switch to the current stage, enter ``stage``; returns
        the stage left (to switch back to after nested work)."""
        if not self.enabled:
            return None
        now = self._now()
        left = self._stage
        if left is not None:
            self.seconds[left] = self.seconds.get(left, 0.0) + now - self._since
        self._stage, self._since = stage, now
        return left

    def stop(self) -> None:
        """End of a frame: charge the current stage, enter none."""
        self.switch(None)
