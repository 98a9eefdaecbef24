"""How often Python hands the GIL between threads in a node process (or the composed graph).

A node runs several threads: the executor (callbacks, message conversion), its worker, the
multi-view filter's feed, the adaptation's training. Torch and numpy release the GIL inside
each operation, but between operations a thread needs it back; with Python's default switch
interval (5 ms) a thread that has just released it waits up to 5 ms behind any thread busy in
Python, at every one of its hundreds of small operations per keyframe. A 0.5 ms interval
measured, composed graph on 2 cores, `depth-fusion bench --only node_graph`, paced, two runs
each: 3.0-3.1 kf/s against 2.3-2.4, median latency 491-558 ms against 592-602 ms.

``DEPTH_FUSION_GIL_SWITCH_S`` overrides it (seconds; Python's default is 0.005).
"""

from __future__ import annotations

import os
import sys

#: The interval the graph's processes use unless ``DEPTH_FUSION_GIL_SWITCH_S`` says otherwise.
SWITCH_INTERVAL_S = 0.0005
ENV = 'DEPTH_FUSION_GIL_SWITCH_S'


def configured_interval() -> float:
    """The interval to use: the environment's when it is a positive number, else the default."""
    text = os.environ.get(ENV, '').strip()
    if not text:
        return SWITCH_INTERVAL_S
    message = f'{ENV} must be a positive number of seconds, got {text!r}'
    try:
        value = float(text)
    except ValueError:
        raise ValueError(message) from None
    if not value > 0:
        raise ValueError(message)
    return value


def set_switch_interval() -> float:
    """Apply :func:`configured_interval`; returns the interval it replaced (to restore it)."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(configured_interval())
    return previous
