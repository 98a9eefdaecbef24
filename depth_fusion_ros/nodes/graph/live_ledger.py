"""What ``depth-fusion launch`` hears of its graph: the nodes' keyframe events, counted.

``depth-fusion run`` ends with a count of every keyframe the policy chose and what became of
it (fused, or dropped and why). A live launch ended with "3 nodes stopped cleanly": keyframes
the multi-view node dropped for a full queue were only in its log. This listens to the same
events (``graph_events``, one reliable topic) on the launch's ROS domain, with its own context
and one executor thread, so the launch can say the same count when it stops.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from ..graph_events import KeyframeLedger, LedgerSnapshot, subscribe_events

log = logging.getLogger(__name__)

#: The listener's node name on the graph.
NODE_NAME = 'depth_fusion_launch'


class LiveLedger:
    """A keyframe ledger fed by the events on this process's ROS domain (``ROS_DOMAIN_ID``)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.ledger = KeyframeLedger()
        self._context = rclpy.context.Context()
        rclpy.init(args=[], context=self._context)
        self._node = rclpy.create_node(NODE_NAME, context=self._context)
        self._subs = subscribe_events(self._node, self.ledger)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._thread = threading.Thread(target=self._spin, name='launch-ledger', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except Exception as exc:  # the context shut down under it at close
            if self._context.ok():
                log.warning('the keyframe count stopped listening (%r)', exc)

    def snapshot(self) -> LedgerSnapshot:
        return self.ledger.snapshot()

    def close(self) -> None:
        self._executor.shutdown(timeout_sec=2.0)
        self._node.destroy_node()
        self._context.try_shutdown()
        self._thread.join(5.0)


def start_listening() -> Any:
    """A :class:`LiveLedger`, or ``None`` (said once) where rclpy cannot start here: the launch
    then goes on without its count."""
    try:
        return LiveLedger()
    except Exception as exc:  # no DDS here: the nodes may still run; say what is missing
        log.warning('no keyframe count at the stop: cannot listen to the graph (%s)', exc)
        return None
