"""Run the depth filter over a recorded sequence, frame by frame, for any frame asked for.

The evaluation asks for the multi-view depth of keyframes in increasing order; the filter
must still see *every* posed frame in between, in order, as the node does. A stream keeps
the filter and the index of the next frame to feed; asking for an earlier frame than the
last one restarts it from the first frame (the filter is causal, it cannot go back).

``lookahead``: the estimate of frame ``k`` is taken after the filter has seen frames up to
``k + lookahead`` and warped into ``k`` (the offline evaluation, like the sweep's offline
neighbours on both sides of a keyframe; a node could do the same at ``lookahead`` frames
of latency). 0 = causal, what the node publishes.

A fixed-lag read: the filter's keyframe moves on during the look-ahead, and the estimates of
pixels of ``k`` that the new keyframe no longer sees are not carried. With ``keyframes``
(the frames that will be asked for), the stream therefore also reads each of them from every
filter keyframe it leaves inside the window, just before the switch, and the answer is the
final read with its holes filled from those (latest first): what the filter knew of frame
``k``'s pixels during the window. On a rotation-heavy synthetic sequence the final read alone
had no estimate in the quarter of the image that had left the view (docs/multi_view.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from ..camera import PinholeCamera
from .filter import KEYFRAME, DepthFilter
from .filter_config import FilterConfig
from .filter_result import FilterResult, fill_missing
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
        keyframes: Sequence[int] = (),
    ) -> None:
        if lookahead < 0:
            raise ValueError(f'lookahead must be >= 0, got {lookahead}')
        self.lookahead = int(lookahead)
        self.num_frames = num_frames
        self._frame = frame
        self._make = lambda: DepthFilter(camera, config, matching, device)
        self.keyframes = sorted(set(int(k) for k in keyframes))
        self.filter = self._make()
        self.next_index = 0
        #: Reads of asked-for frames from filter keyframes left during their window.
        self._left: dict[int, list[FilterResult]] = {}

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
            self._left.clear()
        while self.next_index <= last:
            gray, pose = self._frame(self.next_index)
            before = self.filter.key
            if self.filter.process(gray, pose) == KEYFRAME and before is not None:
                self._read_leaving(before, self.next_index)
            self.next_index += 1
        result = self.filter.result(self._frame(index)[1])
        for earlier in reversed(self._left.pop(index, [])):
            result = fill_missing(result, earlier)
        return result

    def _read_leaving(self, keyframe: object, switch: int) -> None:
        """Read the asked-for frames whose window holds ``switch`` from the keyframe being left."""
        if self.lookahead == 0:
            return
        for k in self.keyframes:
            if k < switch <= k + self.lookahead:
                self._left.setdefault(k, []).append(self.filter.result(self._frame(k)[1], keyframe))
