"""Building the fusion kernels ahead of time in a process of its own, at the lowest CPU priority.

A fusion node that finds no kernels built ahead of time (a machine where nobody ran
``depth-fusion kernels``, or weight parameters other than the defaults) used to compile them
with ``torch.compile`` in its own process at every start: on 2 cores 15-25 s during which the
compile takes a core and, tracing in Python, the GIL from the node's worker, so a live camera
started with it lost keyframes (18 of 49 on a 7-Scenes stretch, against 0 with the kernels
built; docs/performance.md, "A cold machine"). Instead the node starts this module as a
separate process at the lowest CPU priority: it builds the kernels with AOTInductor into the
user cache (~45 s of otherwise idle CPU) while the node fuses with the eager kernels; the node
then loads them, and every later start is warm within a few seconds.

    python -m depth_fusion_ros.fusion.aot_background '{"sigma1": 15.0, ...}'
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

from ..priority import idle_policy, lower_priority
from .weights import WeightParams

#: The builder's output (one line per kernel, or the reason it failed), next to the kernels.
LOG_NAME = 'background_build.log'


def spawn(params: WeightParams, cache: Path) -> subprocess.Popen:
    """Start the builder for ``params`` (a process of its own session: a Ctrl-C meant for the
    graph does not stop it half-way, and a finished build is simply there at the next start).
    Its output goes to ``cache / LOG_NAME``."""
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / LOG_NAME, 'ab') as log:
        return subprocess.Popen(
            [sys.executable, '-m', __name__, json.dumps(dataclasses.asdict(params))],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def _lowest_priority() -> None:
    """This process and the compiler processes it starts at the lowest CPU priority there is:
    nice 19 and ``SCHED_IDLE``, and, where the kernel groups processes by session
    (``sched_autogroup``, the default on desktop Linux), the nice value of this process's own
    session group, without which the builder would get as much CPU as the whole graph's
    session (measured: 48 % of a core beside a live graph, with 17 keyframes lost to it).
    Each step is best effort: a build at a higher priority is still a one-off."""
    lower_priority(19)
    idle_policy()
    with contextlib.suppress(OSError):
        Path('/proc/self/autogroup').write_text('19')


def main(argv: list[str]) -> int:
    """Lowest priority first, then the build under the cache's lock (0 also when another
    builder made the kernels meanwhile)."""
    _lowest_priority()
    if len(argv) != 2:
        print('usage: python -m depth_fusion_ros.fusion.aot_background WEIGHT_PARAMS_JSON', flush=True)
        return 2
    params = WeightParams(**json.loads(argv[1]))

    import torch

    from . import aot_kernels

    try:
        seconds = aot_kernels.build_if_missing(params, wait=True)  # a second node waits for the first's build
    except Exception as exc:  # no C++ compiler, an export this torch cannot do: one line
        print(f'background build failed ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})', flush=True)
        return 1
    if not seconds:
        print('the kernels were built meanwhile by another process', flush=True)
    for name, took in (seconds or {}).items():
        target = aot_kernels.package_path(name, params, torch.device('cpu'))
        print(f'{name}: built in {took:.1f} s -> {target}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
