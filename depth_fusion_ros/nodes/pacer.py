"""Back-pressure for a replay: never send the next keyframe's images while the graph is busy.

A bag replayed at the recorded rate into a graph that is slower than the camera loses
keyframes (queues overflow) or, with blocking queues, piles them up in DDS histories. A paced
replay instead follows the graph's own progress (:mod:`.graph_events`): before each camera
image it waits until

* fewer than ``max_keyframes`` chosen keyframes are still in flight (no fused depth nor drop
  announced yet), and
* fewer than ``max_images_ahead`` images sent are not yet handled by the multi-view node (so
  the replayer knows whether an image became a keyframe before it sends the next keyframe's
  images).

It never plays faster than the recorded rate (times ``rate``): a graph that keeps up sees the
recorded timing, a slow one fuses every keyframe, only later. If the graph stops reporting
progress for ``timeout`` seconds (no graph, a node that died), pacing is switched off with a
warning and the replay goes on at the recorded rate.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .graph_events import KeyframeLedger, ReadyWatcher, subscribe_events


@dataclass
class PaceStats:
    """How much the graph held the replay back."""

    pauses: int = 0
    paused_s: float = 0.0
    gave_up: bool = False


class Pacer:
    """The replayer's view of the graph's progress, and the wait before each image."""

    def __init__(
        self,
        node: Any,
        *,
        max_keyframes: int,
        max_images_ahead: int,
        timeout: float,
        stop: threading.Event,
        warn: Callable[[str], None],
        enabled: bool = True,
    ) -> None:
        self.ledger = KeyframeLedger()
        self.ready = ReadyWatcher()
        self._subs = subscribe_events(node, self.ledger, self.ready)
        self.max_keyframes = int(max_keyframes)
        self.max_images_ahead = int(max_images_ahead)
        self.timeout = float(timeout)
        self.enabled = enabled
        self.stats = PaceStats()
        self._stop = stop
        self._warn = warn
        self._unacked: deque[int] = deque()

    def _busy(self) -> str:
        """Why the next image must wait ('' when it may go)."""
        acked = self.ledger.last_image_ns
        while self._unacked and self._unacked[0] <= acked:
            self._unacked.popleft()
        if len(self._unacked) >= self.max_images_ahead:
            return f'{len(self._unacked)} images not yet handled by the multi-view node'
        in_flight = self.ledger.in_flight()
        if in_flight >= self.max_keyframes:
            return f'{in_flight} keyframes in flight'
        return ''

    def before_image(self) -> bool:
        """Wait until the graph can take the next image; ``False`` when playback is stopped."""
        if not self.enabled:
            return not self._stop.is_set()
        why = self._busy()
        if not why:
            return not self._stop.is_set()
        start = time.monotonic()
        self.stats.pauses += 1
        while why and not self._stop.is_set():
            now = time.monotonic()
            if now - max(self.ledger.last_event, start) > self.timeout:
                self._warn(
                    f'no progress from the graph for {self.timeout:g} s ({why}): pacing off, '
                    'playing at the recorded rate from now on'
                )
                self.enabled = False
                self.stats.gave_up = True
                break
            self.ledger.wait(0.05)
            why = self._busy()
        self.stats.paused_s += time.monotonic() - start
        return not self._stop.is_set()

    def sent_image(self, stamp_ns: int) -> None:
        if self.enabled:
            self._unacked.append(stamp_ns)
