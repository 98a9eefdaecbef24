"""Paced (lossless) or real-time replay: what the runner tells the replayer and the nodes.

* **paced** (default): the replayer follows the graph's progress (``pace``): it sends the next
  images only while fewer than ``max_keyframes_in_flight`` chosen keyframes are unfinished, so
  a slow machine fuses every keyframe, later. The nodes' work queues block instead of dropping
  (``queue_policy: block``) as a second guard: with pacing they never fill in practice. Nothing
  trades quality for time either: the filter sees every frame (``filter.max_lag_frames: 0``)
  and the fusion keeps all its points while a keyframe waits (``load_max_points: 0``).
* **real time** (``--realtime``): the bag plays at its recorded rate whatever the graph does,
  with the nodes' own queue policies; what is lost is counted and reported by reason.

Either way the replayer starts once every node said it is ready (``wait_ready``, see
:mod:`depth_fusion_ros.nodes.graph_events`) and its publishers are matched with the
subscriptions the nodes named: no fixed delay and no graph introspection. Then it waits up to
``warm_timeout`` s (``wait_warm``) for a node that warms up in the background (the fusion
node compiling its kernels) to say it is warm: a replay then meets the graph at full speed
instead of sharing the cores with the compiler for its first seconds.
"""

from __future__ import annotations

from typing import Any

from .options import RunOptions
from .param_merge import param_from_file, read_params_file
from .topics import GRAPH_NODES, REPLAYER, graph_nodes


def paced_overrides(options: RunOptions, overrides: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``overrides`` with the replayer's start and pacing settings and the nodes' queue policy.

    What the user set (``--set`` or the params file) wins over these defaults.
    """
    params = read_params_file(options.params_file)
    user = options.overrides

    def unset(node: str, name: str) -> bool:
        return name not in user.get(node, {}) and param_from_file(params, node, name) is None

    out = {node: dict(values) for node, values in overrides.items()}
    replayer = out.setdefault(REPLAYER[0], {})
    paced = not options.realtime
    for name, value in (
        ('wait_ready', list(graph_nodes(options.with_map))),
        ('wait_for_nodes', ['']),  # replaced by the nodes' own ready lines
        ('start_delay', 0.0),
        ('wait_timeout', float(options.startup_timeout)),
        ('wait_warm', float(options.warm_timeout)),
        ('pace', paced),
    ):
        if unset(REPLAYER[0], name):
            replayer[name] = value
    if paced and options.max_keyframes_in_flight is not None:
        replayer['max_keyframes_in_flight'] = int(options.max_keyframes_in_flight)
    if paced:
        for node in GRAPH_NODES:
            if unset(node, 'queue_policy'):
                out.setdefault(node, {})['queue_policy'] = 'block'
        for name in ('filter.max_lag_frames', 'filter.max_update_rate'):  # the filter sees every frame
            if unset('multi_view_node', name):
                out.setdefault('multi_view_node', {})[name] = 0
        if unset('fusion_node', 'load_max_points'):  # nothing is lost by waiting: full quality
            out.setdefault('fusion_node', {})['load_max_points'] = 0
    return out
