"""``diagnostic_msgs/DiagnosticArray`` on ``/diagnostics``: the ROS convention for node health.

rqt_robot_monitor, diagnostic_aggregator and fleet tools read ``/diagnostics``; a node that
only logs counters is invisible to them. Every processing node publishes one
``DiagnosticStatus`` named ``depth_fusion/<node name>`` once per ``diagnostics_period``,
built here from its :class:`~.stats.NodeStats` and a few node-specific values:

* key/values: input rates (Hz over the last period), received / processed / published
  counts, dropped and noted counts by reason, the worker queue depth, latency, readiness;
* level **OK**; **WARN** when more than ``diagnostics_drop_share`` of the inputs received over
  the last ``DROP_WINDOW_S`` seconds were dropped, or the node is not ready yet; **ERROR** when
  an input is missing: a required stream has not arrived for ``diagnostics_input_timeout``
  seconds while the stream that needs it keeps arriving (e.g. images but no pose).

Building the status is pure (:func:`assess`, :func:`status_values`), so it is tested without
DDS; :class:`Diagnostics` holds the rate and window state and makes the message.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .params import ParamSpec
from .stats import StatsSnapshot

TOPIC_DIAGNOSTICS = '/diagnostics'
NAME_PREFIX = 'depth_fusion/'
#: Seconds over which the drop share is measured (long enough to be stable at 1 Hz).
DROP_WINDOW_S = 10.0
OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR'}

PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'diagnostics_period',
        1.0,
        'seconds between two DiagnosticArray messages on /diagnostics (0: none)',
        0.0,
        3600.0,
    ),
    ParamSpec(
        'diagnostics_drop_share',
        0.1,
        f'status WARN when more than this share of the inputs of the last {DROP_WINDOW_S:g} s was dropped',
        0.0,
        1.0,
    ),
    ParamSpec(
        'diagnostics_input_timeout',
        5.0,
        'status ERROR when a required input (e.g. the pose) has not arrived for this many seconds '
        'while the input that needs it (e.g. the image) keeps arriving',
        0.1,
        86400.0,
    ),
)


@dataclass(frozen=True)
class Requirement:
    """``needed`` must keep arriving while ``while_receiving`` does (stream names of NodeStats)."""

    needed: str
    while_receiving: str
    #: What to tell the user (e.g. the topic name).
    hint: str = ''


@dataclass(frozen=True)
class Assessment:
    level: int
    message: str


def missing_inputs(
    requirements: Sequence[Requirement],
    first_seen: Mapping[str, float],
    last_seen: Mapping[str, float],
    now: float,
    timeout: float,
) -> list[str]:
    """One phrase per requirement violated now (``'no pose for 6.0 s while image arrives'``)."""
    out = []
    for req in requirements:
        active = last_seen.get(req.while_receiving)
        if active is None or now - active > timeout:
            continue  # the stream that needs it is quiet too: nothing is missing *now*
        since = last_seen.get(req.needed, first_seen.get(req.while_receiving, now))
        if now - since > timeout:
            never = req.needed not in last_seen
            what = f'no {req.needed} {"yet" if never else f"for {now - since:.1f} s"}'
            hint = f' ({req.hint})' if req.hint else ''
            out.append(f'{what} while {req.while_receiving} arrives{hint}')
    return out


def assess(
    drop_share: float,
    max_share: float,
    missing: Sequence[str],
    ready: bool,
    waiting_for: str,
    warnings: Sequence[str] = (),
) -> Assessment:
    """Level and one-line message of a status (ERROR > WARN > OK; every reason is named)."""
    if missing:
        return Assessment(ERROR, '; '.join(missing))
    reasons = []
    if drop_share > max_share:
        reasons.append(f'{drop_share:.0%} of the recent inputs dropped (more than {max_share:.0%})')
    if not ready:
        reasons.append(f'not ready: waiting for {waiting_for}')
    reasons.extend(warnings)
    if reasons:
        return Assessment(WARN, '; '.join(reasons))
    return Assessment(OK, 'running')


def status_values(
    snap: StatsSnapshot,
    rates: Mapping[str, float],
    queue_depth: int,
    ready: bool,
    extra: Mapping[str, Any],
) -> list[tuple[str, str]]:
    """The key/values of a status, in a stable order (counters by reason are sorted)."""
    values = [('ready', str(ready).lower())]
    values += [(f'rate {k} (Hz)', f'{v:.2f}') for k, v in sorted(rates.items())]
    values += [(f'received {k}', str(v)) for k, v in sorted(snap.received.items())]
    values.append(('processed', str(snap.processed)))
    values += [(f'published {k}', str(v)) for k, v in sorted(snap.published.items())]
    values.append(('dropped total', str(snap.dropped_total)))
    values += [(f'dropped {k}', str(v)) for k, v in sorted(snap.dropped.items())]
    values += [(f'noted {k}', str(v)) for k, v in sorted(snap.noted.items())]
    values.append(('queue depth', str(queue_depth)))
    if snap.processed:
        values.append(('latency mean (ms)', f'{snap.latency_mean_s * 1000:.1f}'))
        values.append(('latency max (ms)', f'{snap.latency_max_s * 1000:.1f}'))
    values += [(str(k), str(v)) for k, v in extra.items()]
    return values


class Diagnostics:
    """Rates and the drop window between two publications; builds the ``DiagnosticArray``."""

    def __init__(self, name: str, hardware_id: str, max_share: float, timeout: float) -> None:
        self.name = NAME_PREFIX + name
        self.hardware_id = hardware_id
        self.max_share = max_share
        self.timeout = timeout
        self._last: tuple[float, dict[str, int]] | None = None
        #: (time, received total, dropped total) over the last DROP_WINDOW_S
        self._window: deque[tuple[float, int, int]] = deque()
        self.last_assessment = Assessment(OK, 'starting')

    def _rates(self, now: float, received: Mapping[str, int]) -> dict[str, float]:
        rates: dict[str, float] = {}
        if self._last is not None and now > self._last[0]:
            dt = now - self._last[0]
            rates = {k: (v - self._last[1].get(k, 0)) / dt for k, v in received.items()}
        self._last = (now, dict(received))
        return rates

    def _drop_share(self, now: float, snap: StatsSnapshot) -> float:
        received, dropped = sum(snap.received.values()), snap.dropped_total
        self._window.append((now, received, dropped))
        while len(self._window) > 1 and now - self._window[0][0] > DROP_WINDOW_S:
            self._window.popleft()
        if len(self._window) < 2:
            return dropped / received if received else 0.0
        _, r0, d0 = self._window[0]
        return (dropped - d0) / (received - r0) if received > r0 else 0.0

    def array(
        self,
        stamp: Any,
        snap: StatsSnapshot,
        arrivals: tuple[Mapping[str, float], Mapping[str, float]],
        requirements: Sequence[Requirement],
        queue_depth: int,
        ready: bool,
        waiting_for: str,
        extra: Mapping[str, Any],
        warnings: Sequence[str] = (),
        now: float | None = None,
    ) -> Any:
        """The ``DiagnosticArray`` of this instant (one status)."""
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        now = time.monotonic() if now is None else now
        rates = self._rates(now, snap.received)
        share = self._drop_share(now, snap)
        missing = missing_inputs(requirements, arrivals[0], arrivals[1], now, self.timeout)
        self.last_assessment = assess(share, self.max_share, missing, ready, waiting_for, warnings)
        values = status_values(
            snap, rates, queue_depth, ready, {'drop share (recent)': f'{share:.3f}', **extra}
        )
        status = DiagnosticStatus(
            level=bytes([self.last_assessment.level]),
            name=self.name,
            message=self.last_assessment.message,
            hardware_id=self.hardware_id,
            values=[KeyValue(key=k, value=v) for k, v in values],
        )
        array = DiagnosticArray(status=[status])
        array.header.stamp = stamp
        return array


def replayer_array(
    name: str, stamp: Any, published: Mapping[str, int], passes: int, max_lag_s: float, state: str, error: str
) -> Any:
    """The bag_replayer's ``DiagnosticArray``: what it played; ERROR when playback failed."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    values = [('state', state), ('passes', str(passes)), ('max lag (ms)', f'{max_lag_s * 1000:.1f}')]
    values += [(f'published {k}', str(v)) for k, v in sorted(published.items())]
    status = DiagnosticStatus(
        level=bytes([ERROR if error else OK]),
        name=NAME_PREFIX + name,
        message=f'playback failed: {error}' if error else state,
        hardware_id='bag',
        values=[KeyValue(key=k, value=v) for k, v in values],
    )
    array = DiagnosticArray(status=[status])
    array.header.stamp = stamp
    return array
