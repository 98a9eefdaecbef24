"""Counters every node keeps (received, processed, dropped by reason, latency) and throttled warnings.

A node that drops a message must say so (a user chasing a missing keyframe reads the log)
but must not flood the log at 30 Hz when a whole stream is bad. So each *reason* (e.g.
``no_camera_info``, ``bad_quaternion``) is counted separately and warned about at most once
per ``throttle`` seconds, the warning saying how many more were dropped since the last one.
The counters are logged periodically and once more at shutdown, and tests read them through
:meth:`NodeStats.snapshot` instead of parsing logs.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class StatsSnapshot:
    """A consistent copy of a node's counters at one instant."""

    received: dict[str, int] = field(default_factory=dict)
    processed: int = 0
    published: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    #: Anomalies that still produced an output (fusion fallbacks ...), by reason.
    noted: dict[str, int] = field(default_factory=dict)
    latency_mean_s: float = float('nan')
    latency_max_s: float = float('nan')
    #: Plain tallies by group and key (e.g. ``{'decision': {'full': 12, 'scale_only': 2}}``).
    counts: dict[str, dict[str, int]] = field(default_factory=dict)

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())

    def summary(self) -> str:
        """One log line: ``received image=30 pose=90 | processed 5 | dropped 2 (no_pose=2) | ...``."""

        def fmt(counts: dict[str, int]) -> str:
            return ' '.join(f'{k}={v}' for k, v in sorted(counts.items())) or '0'

        latency = (
            f'latency mean {self.latency_mean_s * 1000:.1f} ms max {self.latency_max_s * 1000:.1f} ms'
            if self.processed
            else 'latency n/a'
        )
        dropped = f'dropped {self.dropped_total}' + (f' ({fmt(self.dropped)})' if self.dropped else '')
        noted = f' | noted {fmt(self.noted)}' if self.noted else ''
        counts = ''.join(f' | {group} {fmt(c)}' for group, c in sorted(self.counts.items()))
        return (
            f'received {fmt(self.received)} | processed {self.processed} | published {fmt(self.published)}'
            f' | {dropped}{noted}{counts} | {latency}'
        )


class NodeStats:
    """Thread-safe counters of one node; callbacks and the worker thread both update them."""

    def __init__(self, warn: Callable[[str], None], throttle: float = 5.0) -> None:
        self._warn = warn
        self.throttle = throttle
        self._lock = threading.Lock()
        self._received: Counter[str] = Counter()
        self._published: Counter[str] = Counter()
        self._dropped: Counter[str] = Counter()
        self._noted: Counter[str] = Counter()
        self._counts: dict[str, Counter[str]] = {}
        self._processed = 0
        #: stream -> monotonic time of its first / latest message (diagnostics: missing inputs)
        self._first_seen: dict[str, float] = {}
        self._last_seen: dict[str, float] = {}
        self._latency_sum = 0.0
        self._latency_max = 0.0
        #: reason -> (monotonic time of the last warning, drops since then)
        self._last_warning: dict[str, tuple[float, int]] = {}

    def received(self, stream: str) -> None:
        now = time.monotonic()
        with self._lock:
            self._received[stream] += 1
            self._first_seen.setdefault(stream, now)
            self._last_seen[stream] = now

    def arrival_times(self) -> tuple[dict[str, float], dict[str, float]]:
        """``(first, latest)`` monotonic arrival time per input stream."""
        with self._lock:
            return dict(self._first_seen), dict(self._last_seen)

    def published(self, stream: str) -> None:
        with self._lock:
            self._published[stream] += 1

    def processed(self, latency_s: float) -> None:
        """One unit of work done; ``latency_s`` from the input's arrival to the output's publication."""
        with self._lock:
            self._processed += 1
            self._latency_sum += latency_s
            self._latency_max = max(self._latency_max, latency_s)

    def count(self, group: str, key: str) -> None:
        """Tally an outcome that is neither a drop nor an anomaly (e.g. the fusion's decision)."""
        with self._lock:
            self._counts.setdefault(group, Counter())[key] += 1

    def dropped(self, reason: str, message: str = '', count: int = 1) -> None:
        """Count ``count`` inputs dropped for ``reason`` and warn (throttled per reason).

        ``message`` says what was wrong with this input; it is logged with the reason so the
        log names the problem, not just a counter.
        """
        self._count_and_warn(self._dropped, 'dropped', reason, message, count)

    def noted(self, reason: str, message: str = '', count: int = 1) -> None:
        """Count ``count`` anomalies that did not cost an output (e.g. a fusion fallback) and
        warn, throttled."""
        self._count_and_warn(self._noted, 'note', reason, message, count)

    def _count_and_warn(
        self, counter: Counter[str], verb: str, reason: str, message: str, count: int
    ) -> None:
        now = time.monotonic()
        key = f'{verb}:{reason}'
        with self._lock:
            counter[reason] += count
            last, suppressed = self._last_warning.get(key, (-float('inf'), 0))
            if now - last < self.throttle:
                self._last_warning[key] = (last, suppressed + count)
                return
            self._last_warning[key] = (now, 0)
        more = f' ({suppressed} more since the last warning)' if suppressed else ''
        self._warn(f'{verb} [{reason}]: {message or reason}{more}')

    def snapshot(self) -> StatsSnapshot:
        with self._lock:
            n = self._processed
            return StatsSnapshot(
                received=dict(self._received),
                processed=n,
                published=dict(self._published),
                dropped=dict(self._dropped),
                noted=dict(self._noted),
                latency_mean_s=self._latency_sum / n if n else float('nan'),
                latency_max_s=self._latency_max if n else float('nan'),
                counts={group: dict(c) for group, c in self._counts.items()},
            )
