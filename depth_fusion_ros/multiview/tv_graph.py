"""The TV baseline's iterations as one CUDA graph, captured once per shape and replayed per keyframe.

Why: on a GPU the coupled iterations (``tv.iterate``: 47 primal-dual steps and point
searches, about 800 small kernels) cost their Python launch overhead, not arithmetic: 76 ms
a keyframe on an H200 for a few milliseconds of GPU work (docs/performance.md, "GPU").

A graph needs shapes that do not depend on the data. The only data-dependent shape is the
point search's window, sized from the keyframe's cost range. Here it is sized from the
bound on that range instead: a ``1 - ZNCC`` cost lies in [0, 2] and the data weight is at
most ``data_weight``, so the range is at most ``2 * data_weight``. A wider window only adds
samples that can (almost) never win (``tv.window_radius``): on the plane scene 0.1 % of the
pixels move, by 1e-5 on average (``test_multiview_tv.py``). A range over the bound (never
seen) runs the eager loop, logged.
"""

from __future__ import annotations

import functools
import logging

import torch

from ..cuda_graph import GraphCache
from .tv import TVConfig, iterate, theta_schedule, window_radius

log = logging.getLogger(__name__)

GRAPHS = GraphCache('tv')


def cost_bound(config: TVConfig) -> float:
    """Largest possible cost range of the weighted volume: ``1 - ZNCC`` in [0, 2] times the weight."""
    return 2.0 * config.data_weight


@functools.lru_cache(maxsize=8)
def _schedule_on(config: TVConfig, device: torch.device) -> torch.Tensor:
    """The theta schedule on the device: a host copy, so made once (never while capturing)."""
    return torch.tensor(theta_schedule(config), dtype=torch.float32, device=device)


def run_graphed(
    weighted: torch.Tensor, g: torch.Tensor, a: torch.Tensor, config: TVConfig
) -> torch.Tensor | None:
    """``tv.iterate`` replayed from a cached CUDA graph, or None where the caller must run it eagerly.

    None when capturing failed for this shape, or when this keyframe's cost range exceeds
    :func:`cost_bound` (a window sized from the bound could then miss the winner).
    """
    bound = cost_bound(config)
    cost_range = float((weighted.max(dim=1).values - weighted.min(dim=1).values).max())
    if cost_range > bound * (1.0 + 1e-6):
        log.warning('tv: cost range %.4g over its bound %.4g; running eagerly', cost_range, bound)
        return None
    radii = [window_radius(theta, bound, weighted.shape[1]) for theta in theta_schedule(config)]
    theta_t = _schedule_on(config, a.device)
    key = (weighted.device, tuple(weighted.shape), tuple(g.shape), config)

    def loop(*inputs: torch.Tensor) -> torch.Tensor:
        return iterate(*inputs[:3], config, radii, inputs[3])

    out = GRAPHS.run(key, loop, (weighted, g, a, theta_t))
    return None if out is None else out[0]
