"""Seconds of every adaptation update, in the bench's order, and where the host time goes.

    python scripts/diag/adapt_update_times.py [--device cuda]

``depth-fusion bench --only adaptation --device cuda`` gave 1.15 s a keyframe update on an
H200 (2026-11-27) while ``cuda_host_split.py`` gave 0.16 s for the same update repeated on
keyframes already seen. This replays the bench as it was then (same samples, a fixed warm-up
of 5 keyframes observed, then 7 new keyframes: the order that showed the artefact; the bench
now warms up with ``bench.adaptation._warm_up``) with every update synchronised and timed,
then the same 7 again, with cProfile over the first pass of the timed keyframes (own time,
top 25).

``--cudnn on|off|benchmark`` runs the same with cuDNN on (torch's default), disabled (torch's
own convolution kernels) or autotuning, whatever the adapter would choose; the default,
``adapter``, is the adapter's own choice (cuDNN off while it trains on a GPU since 2026-12-04:
the first updates of a process took seconds each in ``conv2d``, once per new batch shape,
docs/adaptation.md). One process per setting: that cost is per process.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import pstats
import time

import torch

from depth_fusion_ros.adaptation.adapter import Adapter
from depth_fusion_ros.adaptation.config import AdaptConfig
from depth_fusion_ros.bench.adaptation import _samples


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--device', default='cuda' if torch.cuda.is_available() else 'cpu')
    ap.add_argument('--cudnn', choices=('adapter', 'on', 'off', 'benchmark'), default='adapter')
    ap.add_argument('--no-profile', action='store_true', help='print the timings only')
    a = ap.parse_args()
    if a.cudnn != 'adapter':  # the flags below, not the adapter's switch
        Adapter._convolutions = lambda self: contextlib.nullcontext()
        torch.backends.cudnn.enabled = a.cudnn != 'off'
        torch.backends.cudnn.benchmark = a.cudnn == 'benchmark'
    sync = torch.cuda.synchronize if a.device.startswith('cuda') else (lambda: None)
    config = AdaptConfig()
    warm = 1 + max(config.guard_keyframes, config.replay_per_step)
    samples = _samples(warm + 7)
    adapter = Adapter.from_spec('default', config, a.device)

    times: dict[str, list[float]] = {}

    def observe(s, tag: str) -> None:
        sync()
        t0 = time.perf_counter()
        r = adapter.observe(s)
        sync()
        ms = 1e3 * (time.perf_counter() - t0)
        times.setdefault(tag, []).append(ms)
        print(f'{tag} key {s.key}: {ms:8.1f} ms  {r.status}', flush=True)

    for s in samples[:warm]:
        observe(s, 'warm')
    pr = cProfile.Profile()
    pr.enable()
    for s in samples[warm:]:
        observe(s, 'timed')
    pr.disable()
    for s in samples[warm:]:
        observe(s, 'again')
    summary = ', '.join(
        f'{tag} sum {sum(v) / 1e3:.2f} s max {max(v):.0f} ms median {sorted(v)[len(v) // 2]:.0f} ms'
        for tag, v in times.items()
    )
    print(f'cudnn {a.cudnn} on {a.device}: {summary}')
    if a.no_profile:
        return
    out = io.StringIO()
    pstats.Stats(pr, stream=out).sort_stats('tottime').print_stats(25)
    print('\n'.join(ln[:160] for ln in out.getvalue().splitlines() if ln.strip())[-6000:])


if __name__ == '__main__':
    main()
