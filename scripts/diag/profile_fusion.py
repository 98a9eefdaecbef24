"""Time ``fuse_keyframe`` per keyframe inside any ``depth-fusion`` command (diagnostic).

    python scripts/diag/profile_fusion.py evaluate SEQ --frames 60 --stride 5 \
        --single-view simulated --methods fused_fast \
        --set fusion.max_points=4096 --set fusion.stage1=all

(the fusion node's settings: fast mode, compiled kernel, the 4096-point cap, every filter
estimate in stage 1). Prints one line per keyframe (total, stage-1 and Ω points, the guard's
decision, the pipeline's own selection / interpolation timings), a cProfile of the
fusion, guard and selection functions, and the functions with the most own time.
"""

from __future__ import annotations

import cProfile
import pstats
import sys
import time

import depth_fusion_ros.evaluation.methods.fusion as fusion_methods
import depth_fusion_ros.fusion.pipeline as pipeline
from depth_fusion_ros.cli.main import main

_fuse = pipeline.fuse_keyframe
_rows: list[str] = []


def _timed(*args, **kwargs):
    start = time.perf_counter()
    result = _fuse(*args, **kwargs)
    total = time.perf_counter() - start
    steps = ', '.join(f'{k} {v * 1e3:.1f} ms' for k, v in result.timings.items())
    points = f'stage 1 {result.n_stage1:6d}  omega {result.n_omega:5d}'
    _rows.append(f'{total * 1e3:8.1f} ms  {points}  {result.decision}  ({steps})')
    return result


pipeline.fuse_keyframe = _timed
fusion_methods.fuse_keyframe = _timed

if __name__ == '__main__':
    profile = cProfile.Profile()
    profile.enable()
    main(sys.argv[1:])
    profile.disable()
    print('\n'.join(_rows))
    pstats.Stats(profile).sort_stats('cumulative').print_stats('fusion/|guard|selection', 20)
    # Own time of everything the fusion calls (numpy, scipy, torch included): the host's share.
    pstats.Stats(profile).sort_stats('tottime').print_stats(25)
