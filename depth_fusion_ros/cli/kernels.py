"""``depth-fusion kernels``: build the fusion kernels ahead of time so fusion nodes are warm at start,
and the native C kernels (said in one line: how many, for which CPU, or why none)."""

from __future__ import annotations

import argparse

DESCRIPTION = """\
Compile the fusion node's kernels once, ahead of time (torch.export + AOTInductor), into the
user cache (~/.cache/depth_fusion_ros/aot). A fusion node, run or evaluate that finds them is
warm within a second of starting, instead of after a 5-9 s torch.compile in every process
(docs/running.md, "Warm at start"). Run it again after upgrading torch; nodes whose weight
parameters (fusion.sigma1..3, fusion.weights) differ from the defaults compile as before.
It first builds (or finds) the eight native C kernels in ~/.cache/depth_fusion_ros/native and
says for which CPU (an x86-64 with AVX2 and FMA, or an ARM board's own vectors), or why they do
not run here (docs/performance.md, "The native kernels on an ARM robot computer").

examples:
  depth-fusion kernels                # ~17 s on 2 cores
  depth-fusion kernels --if-missing   # what scripts/demo.sh runs: nothing when already built
  depth-fusion kernels --if-missing --background   # what scripts/test.sh runs after the suite
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        'kernels',
        help='build the fusion kernels ahead of time (fusion nodes are then warm at start)',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        '--if-missing',
        action='store_true',
        help='build only when the kernels for this torch, CPU and source are not in the cache yet',
    )
    p.add_argument(
        '--background',
        action='store_true',
        help='build in a process of its own at the lowest CPU priority and return at once (as a fusion '
        "node that finds none does; scripts/test.sh runs it after the suite); output in the cache's log",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from ..fusion import aot_kernels
    from ..fusion.pipeline import FusionConfig

    print(_native_line(), flush=True)
    params = FusionConfig().weight_params
    cpu = torch.device('cpu')
    if not aot_kernels.enabled(cpu):
        print(f'{aot_kernels.ENV_SWITCH}=0 is set: the kernels would be built but never used; unset it')
        return 2
    if args.if_missing and aot_kernels.available(params, cpu):
        print(f'fusion kernels built ahead of time: already in {aot_kernels.cache_dir()}')
        return 0
    if args.background:
        from ..fusion import aot_background

        process = aot_background.spawn(params, aot_kernels.cache_dir())
        log = aot_kernels.cache_dir() / aot_background.LOG_NAME
        print(
            f'building the fusion kernels ahead of time in the background: process {process.pid} at the '
            f'lowest CPU priority (log {log})'
        )
        return 0
    print(
        'building the fusion kernels ahead of time (once; fusion nodes are then warm at start) ...',
        flush=True,
    )
    try:
        if args.if_missing:  # another builder (a fusion node's background build) may finish first
            seconds = aot_kernels.build_if_missing(params, wait=True) or {}
        else:
            with aot_kernels.build_lock(wait=True):
                seconds = aot_kernels.build(params, 'cpu')
    except Exception as exc:  # no C++ compiler, an export this torch cannot do: say it in one line
        print(
            f'depth-fusion kernels: building failed ({type(exc).__name__}: {str(exc).splitlines()[0][:200]})'
        )
        return 1
    if not seconds:
        where = aot_kernels.cache_dir()
        print(f'fusion kernels built ahead of time: built meanwhile by another process, in {where}')
    for name, took in seconds.items():
        print(f'{name}: built in {took:.1f} s -> {aot_kernels.package_path(name, params, cpu)}')
    return 0


def _native_line() -> str:
    """The native C kernels built (the first run on this machine) or found, in one line: a
    user on an ARM board sees at once whether they run there."""
    from .. import native_build, native_kernels
    from ..user_cache import user_cache

    why = native_build.unavailable()
    if why is not None:
        return f'native C kernels: not used here ({why}); their torch and numpy twins run'
    ready, total = native_kernels.prepare(), len(native_kernels.KERNELS)
    target, where = native_build.build_target(), user_cache('native')
    line = f'native C kernels: {ready} of {total} ready for {target} in {where}'
    return line if ready == total else f'{line}; the warnings above say why the others are not'
