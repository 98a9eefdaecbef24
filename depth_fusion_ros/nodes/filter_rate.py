"""Which frames update the filter on a live camera: every one while there is time, fewer when not.

``filter.max_update_rate`` (10 Hz) was chosen on 2 cores when a filter update cost 35-55 ms of
CPU: a 30 Hz camera then gave the filter more than it could take, and the fusion waited
(docs/performance.md, "The filter updated at 10 Hz on a live camera"). An update now costs
about 11 ms, and on a quiet machine every frame makes the estimates better (live TUM fr1_xyz:
fused MAE 0.290 against 0.323 m at 10 Hz); beside two busy loops every frame took the latency
past 0.3 s. So the cap applies only while the machine is short of time, read from the filter's
own updates: when an update takes more than ``load_share`` of the time between two frames
(wall clock against stamp time, both smoothed; ``filter.rate_cap_load``, 1 by default: the
filter could not keep up with every frame), the cap holds; below it, every frame updates. The
wall clock, not CPU time: it counts the cores the rest of the graph and the machine take (live
on the synthetic room an 11 ms update took 15-40 ms). ``load_share`` 0 keeps the cap always
(the rule before 2026-12-02).
"""

from __future__ import annotations

#: Weight of the newest sample in the smoothed update time and frame interval.
SMOOTHING = 0.2
#: Stamp gaps outside (0, this] seconds are not a frame interval (a new stream, a jump).
MAX_GAP_S = 1.0


class UpdateRate:
    """The feed's rule: :meth:`seen` for every frame of the stream as it arrives, :meth:`too_soon`
    for a frame that is not a keyframe, then :meth:`updated` after each update made (its stamp
    and the seconds it took).

    The frame interval is the stream's, read where frames arrive: frames the feed skips because
    it is behind (``filter.max_lag_frames``) never reach it, and read there the interval would
    grow exactly when the feed falls behind, lifting the cap when it is needed most."""

    def __init__(self, max_rate: float, load_share: float) -> None:
        if not (max_rate >= 0 and load_share >= 0):
            raise ValueError(f'max_update_rate and rate_cap_load must be >= 0, got {max_rate}, {load_share}')
        #: Shortest stamp interval (s) between two non-keyframe updates while capped (0: none).
        self.min_interval = 1.0 / max_rate if max_rate > 0 else 0.0
        self.load_share = float(load_share)
        self._last_update: float | None = None
        self._last_seen: float | None = None
        self.update_s: float | None = None
        self.frame_gap_s: float | None = None

    def reset(self) -> None:
        """A new stream: no last update (its first frame always updates); the timings stay (a
        stamp that goes back or jumps is no frame interval: :meth:`seen`)."""
        self._last_update = None

    def loaded(self) -> bool:
        """An update takes more than ``load_share`` of a frame interval (always, with share 0)."""
        if self.load_share <= 0:
            return True
        if self.update_s is None or self.frame_gap_s is None:
            return False
        return self.update_s > self.load_share * self.frame_gap_s

    def too_soon(self, stamp: float) -> bool:
        """Whether a non-keyframe at ``stamp`` is passed over: only while :meth:`loaded`, and
        then when less than ``min_interval`` of stamp time passed since the last update."""
        last = self._last_update
        if self.min_interval <= 0 or last is None or not self.loaded():
            return False
        return 0 <= stamp - last < self.min_interval - 1e-6

    def updated(self, stamp: float, seconds: float) -> None:
        """The filter updated with the frame at ``stamp`` in ``seconds`` (wall clock)."""
        self._last_update = stamp
        self.update_s = _smooth(self.update_s, max(0.0, seconds))

    def seen(self, stamp: float) -> None:
        """A frame of the stream arrived, stamped ``stamp``: the smoothed frame interval."""
        previous, self._last_seen = self._last_seen, stamp
        if previous is not None and previous < stamp and stamp - previous <= MAX_GAP_S:
            self.frame_gap_s = _smooth(self.frame_gap_s, stamp - previous)


def _smooth(old: float | None, new: float) -> float:
    return new if old is None else old + SMOOTHING * (new - old)
