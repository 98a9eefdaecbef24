"""Back-pressure for a replay: never send the next keyframe's images while the graph is busy.

A bag replayed at the recorded rate into a graph that is slower than the camera loses
keyframes (queues overflow) or, with blocking queues, piles them up in DDS histories. A paced
replay instead follows the graph's own progress (:mod:`.graph_events`): before each camera
image it waits until

* fewer than ``max_keyframes`` chosen keyframes are still in flight (no fused depth nor drop
  announced yet), and
* fewer than ``max_images_ahead`` images sent have not reached the multi-view node yet (an
  image that waits there for its pose has reached it: ``image_waiting``), and
* the multi-view node has the last image sent and is done with every image it has posed
  (``image_done``: its depth filter has updated with it), for at most :data:`SETTLE_LIMIT_S`
  per image. Without this the images sent after a fused keyframe went out in a burst (the
  replay is behind its schedule) and queued in front of the filter, and the next keyframe
  waited behind them: 150-200 ms of TUM fr1_xyz's 390-470 ms median latency (measured:
  docs/performance.md, "A paced replay waits for the filter").

Images that wait for their pose hold nothing back: a bag recorded with a SLAM's pose latency
has each pose some frames after its image, and only more images bring it. Until 2026-12-01
the replayer waited for ``max_images_ahead`` images to be *posed*: a pose lag longer than
that deadlocked the replay until ``timeout`` switched pacing off (a 200 ms lag in a 30 Hz bag,
measured). The multi-view node bounds those images itself (``pose_wait``,
``max_pending_images``); a keyframe among them is known, and counted in flight, once posed.

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


#: Seconds one image waits at most for the multi-view node to settle (the last image arrived,
#: the filter done with what it posed); then only the other two rules hold it back. A lost
#: image (it never arrives) costs this once instead of stalling the replay.
SETTLE_LIMIT_S = 1.0
#: Images in front of the filter (on their way, queued or being updated with) when the next is
#: sent, at most. 1: the filter idles for a round trip per image, the next keyframe waits for
#: no frame. Measured against 2 (a keyframe waits behind one frame at most; two runs each of
#: the room and TUM fr1_xyz, paced, processes and composed; docs/performance.md): median
#: latency 196-268 ms against 236-346 ms, keyframes/s 3-6 % lower (means of four runs).
FILTER_DEPTH = 1


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
        #: Images sent that have not reached multi_view_node, oldest first (stamps increase).
        self._unacked: deque[int] = deque()

    def _busy(self, waited: float = 0.0) -> str:
        """Why the next image must wait ('' when it may go)."""
        seen = self.ledger.last_seen_ns
        while self._unacked and self._unacked[0] <= seen:
            self._unacked.popleft()
        if len(self._unacked) >= self.max_images_ahead:
            return f'{len(self._unacked)} images sent have not reached the multi-view node'
        in_flight = self.ledger.in_flight()
        if in_flight >= self.max_keyframes:
            return f'{in_flight} keyframes in flight'
        return self._unsettled() if waited < SETTLE_LIMIT_S else ''

    def _unsettled(self) -> str:
        """Why the multi-view node is not ready for the next image yet ('' when it is): of the
        images sent, more than the newest ``FILTER_DEPTH - 1`` are on their way to it, or its
        filter is not done with all but the newest ``FILTER_DEPTH - 1`` images it posed."""
        depth = FILTER_DEPTH
        if len(self._unacked) >= depth:  # (:meth:`_busy` took out those that arrived)
            return 'an image sent has not reached the multi-view node'
        if self.ledger.last_done_ns < self.ledger.image_ns(depth):
            return 'the multi-view filter is still on an image'
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
            why = self._busy(time.monotonic() - start)
        self.stats.paused_s += time.monotonic() - start
        return not self._stop.is_set()

    def sent_image(self, stamp_ns: int) -> None:
        if self.enabled:
            self._unacked.append(stamp_ns)
