"""Run the depth filter over a recorded sequence, frame by frame, for any frame asked for.

The evaluation asks for the multi-view depth of keyframes in increasing order; the filter
must still see *every* posed frame in between, in order, as the node does. A stream keeps
the filter and the index of the next frame to feed; asking for an earlier frame than the
last one restarts it from the first frame (the filter is causal, it cannot go back).

``lookahead``: the estimate of frame ``k`` is taken after the filter has seen frames up to
``k + lookahead`` and warped into ``k`` (the offline evaluation, like the sweep's offline
neighbours on both sides of a keyframe; a node could do the same at ``lookahead`` frames
of latency). 0 = causal, what the node publishes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..camera import PinholeCamera
from .filter import DepthFilter
from .filter_config import FilterConfig
from .filter_result import FilterResult
from .semidense import MultiViewConfig


class FilterStream:
    """A :class:`DepthFilter` fed from ``frame(i) -> (grey, pose)`` up to the frame asked for."""

    def __init__(
        self,
        frame: Callable[[int], tuple[np.ndarray, np.ndarray]],
        camera: PinholeCamera,
        config: FilterConfig | None = None,
        matching: MultiViewConfig | None = None,
        device: str | torch.device = 'cpu',
        lookahead: int = 0,
        num_frames: int | None = None,
    ) -> None:
        if lookahead < 0:
            raise ValueError(f'lookahead must be >= 0, got {lookahead}')
        self.lookahead = int(lookahead)
        self.num_frames = num_frames
        self._frame = frame
        self._make = lambda: DepthFilter(camera, config, matching, device)
        self.filter = self._make()
        self.next_index = 0

    def result_at(self, index: int) -> FilterResult:
        """The filter's estimate in frame ``index`` after every frame up to it was processed."""
        if index < 0:
            raise ValueError(f'frame index must be >= 0, got {index}')
        last = index + self.lookahead
        if self.num_frames is not None:
            last = min(last, self.num_frames - 1)
        if last < self.next_index - 1:
            self.filter = self._make()
            self.next_index = 0
        while self.next_index <= last:
            gray, pose = self._frame(self.next_index)
            self.filter.process(gray, pose)
            self.next_index += 1
        return self.filter.result(self._frame(index)[1])
