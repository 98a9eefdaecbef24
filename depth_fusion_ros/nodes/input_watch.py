"""Notice two sources mixed on one input: a second publisher, or stamps/frames of two streams.

Two graphs on one ROS domain (two replays, a replay beside a live robot) silently exchange
messages: each node gets both streams and, per message, only drops what goes backwards
(``stamp_out_of_order`` counters). That hides the real problem, so every node also watches
each input topic as a whole and warns **once per topic**, clearly, when

* more than one publisher is on it (``count_publishers``, polled on a timer), naming them;
* its header stamps jump backwards repeatedly (``BACKWARD_JUMPS`` times: one glitch is a
  replay artefact, several are two interleaved clocks);
* its ``header.frame_id`` changes (one camera or pose source keeps one frame).

The current findings are also listed in the node's diagnostics (status WARN).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..data import messages

#: Backward stamp jumps on one topic before it is called interleaved.
BACKWARD_JUMPS = 3
ROS_DOMAIN_HINT = (
    'two sources are mixed: give each run its own ROS_DOMAIN_ID (depth-fusion run does by default) '
    'or remap one of them'
)


@dataclass
class _TopicState:
    last_stamp_ns: int | None = None
    backward: int = 0
    frame_ids: list[str] = field(default_factory=list)


class InputWatch:
    """Per-topic state; ``observe`` is called with every message, ``check_publishers`` on a timer."""

    def __init__(self, warn: Callable[[str], None]) -> None:
        self._warn = warn
        self._topics: dict[str, _TopicState] = {}
        self._warned: set[tuple[str, str]] = set()
        #: topic -> finding, for diagnostics (never cleared: a mix already happened)
        self.findings: dict[str, str] = {}

    def _once(self, topic: str, kind: str, message: str) -> None:
        if (topic, kind) in self._warned:
            return
        self._warned.add((topic, kind))
        self.findings[f'{topic} {kind}'] = message
        self._warn(f'{topic}: {message}; {ROS_DOMAIN_HINT}')

    def observe(self, topic: str, msg: Any) -> None:
        """Track the header of one message of ``topic`` (messages without a header are ignored)."""
        header = getattr(msg, 'header', None)
        if header is None:
            return
        state = self._topics.setdefault(topic, _TopicState())
        stamp = messages.stamp_to_ns(header.stamp)
        if state.last_stamp_ns is not None and stamp < state.last_stamp_ns:
            state.backward += 1
            if state.backward >= BACKWARD_JUMPS:
                self._once(
                    topic,
                    'interleaved',
                    f'header stamps went backwards {state.backward} times (last from '
                    f'{messages.ns_to_sec(state.last_stamp_ns):.3f} to {messages.ns_to_sec(stamp):.3f} s): '
                    'two streams are interleaved',
                )
        state.last_stamp_ns = stamp
        frame = str(header.frame_id)
        if frame not in state.frame_ids:
            state.frame_ids.append(frame)
            if len(state.frame_ids) > 1:
                self._once(
                    topic,
                    'frames',
                    f'header.frame_id changed from {state.frame_ids[0]!r} to {frame!r}: two sources?',
                )

    def check_publishers(self, node: Any, topics: list[str]) -> None:
        """Warn once per topic that has more than one publisher (names them)."""
        for topic in topics:
            resolved = node.resolve_topic_name(topic)
            if node.count_publishers(resolved) <= 1:
                continue
            infos = node.get_publishers_info_by_topic(resolved)
            if len(infos) <= 1:
                continue
            who = ', '.join(sorted(f'{i.node_namespace.rstrip("/")}/{i.node_name}' for i in infos))
            self._once(resolved, 'publishers', f'{len(infos)} publishers ({who})')
