"""Time ``fuse_keyframe`` per keyframe inside any ``depth-fusion`` command (diagnostic).

    python scripts/diag/profile_fusion.py evaluate SEQ --frames 60 --stride 5 \
        --single-view simulated --methods fused_fast \
        --set fusion.max_points=4096 --set fusion.stage1=all

(the fusion node's settings: fast mode, compiled kernel, the 4096-point cap, every filter
estimate in stage 1). Prints one line per keyframe (total, stage-1 and Ω points, the guard's
decision, the pipeline's own selection / interpolation timings), then a cProfile of the
``fuse_keyframe`` calls only, after the first ``WARM_UP`` (so the kernels' compilation and
the rest of the command stay out): the fusion, guard and selection functions by cumulative
time, and every function by own time (numpy, scipy and torch included: the host's share).
``PROFILE_FUSION_CPROFILE=0``: the per-keyframe lines only, timed without the profiler's
overhead (for comparing two commits).
"""

from __future__ import annotations

import cProfile
import os
import pstats
import sys
import time

import depth_fusion_ros.evaluation.methods.fusion as fusion_methods
import depth_fusion_ros.fusion.pipeline as pipeline
from depth_fusion_ros.cli.main import main

#: Keyframes fused before the profile starts (compilation, allocator, first uploads).
WARM_UP = 3

_fuse = pipeline.fuse_keyframe
_rows: list[str] = []
_profile = cProfile.Profile()


_PROFILED = os.environ.get('PROFILE_FUSION_CPROFILE', '1') != '0'


def _timed(*args, **kwargs):
    profiled = _PROFILED and len(_rows) >= WARM_UP
    if profiled:
        _profile.enable()
    start = time.perf_counter()
    result = _fuse(*args, **kwargs)
    total = time.perf_counter() - start
    if profiled:
        _profile.disable()
    steps = ', '.join(f'{k} {v * 1e3:.1f} ms' for k, v in result.timings.items())
    points = f'stage 1 {result.n_stage1:6d}  omega {result.n_omega:5d}'
    _rows.append(f'{total * 1e3:8.1f} ms  {points}  {result.decision}  ({steps})')
    return result


pipeline.fuse_keyframe = _timed
fusion_methods.fuse_keyframe = _timed

if __name__ == '__main__':
    main(sys.argv[1:])
    print('\n'.join(_rows))
    if _PROFILED and len(_rows) > WARM_UP:
        print(f'cProfile of keyframes {WARM_UP + 1}-{len(_rows)}:')
        pstats.Stats(_profile).sort_stats('cumulative').print_stats('fusion/|guard|selection', 30)
        pstats.Stats(_profile).sort_stats('tottime').print_stats(30)
