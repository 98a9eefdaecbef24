"""The fusion's host-side tests on the CPU against their torch paths on a GPU, same inputs.

    python scripts/diag/fusion_gpu_paths.py [--device cuda] [--repeats 30]

A rendered 320x240 room keyframe with a noisy single view and fattened multi-view points on
38 % of the pixels (as the filter's stage 1 gives the fusion node: 20-30k points), then:

* the halo test (``occlusion.halo_points``): NumPy and OpenCV against ``occlusion_gpu.py``;
* the guard's neighbour search (``neighbour_median.nearest_median``) over the node's sample
  of 4096 points: SciPy's k-d tree against the grid search.

Per path: the median wall time of ``repeats`` calls after three warm-up calls (each result is
read back to the host, as the fusion reads it), and whether the two agree. Why: on a GPU the
fusion node is bound by its host (docs/performance.md "GPU"), and a torch path is worth its
second implementation only where it takes less host time than NumPy there.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from depth_fusion_ros.fusion.neighbour_median import nearest_median
from depth_fusion_ros.fusion.occlusion import halo_points
from depth_fusion_ros.fusion.scenes import rendered_halo_keyframe
from depth_fusion_ros.fusion.subsample import seeded_subsample

#: The guard's sample in the fusion node (pipeline.GUARD_SAMPLE_FACTOR x load_max_points).
GUARD_SAMPLE = 4096


def _median_ms(call: Callable[[], object], repeats: int) -> float:
    for _ in range(3):
        call()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--device', default='cuda')
    parser.add_argument('--repeats', type=int, default=30)
    args = parser.parse_args()
    image, single, m, points = rendered_halo_keyframe(320, 240, point_share=0.38)
    print(f'keyframe 320x240, {int(points.sum())} multi-view points; device {args.device}')
    halo = {dev: halo_points(image, single, m, points, device=dev) for dev in ('cpu', args.device)}
    for dev in ('cpu', args.device):
        ms = _median_ms(lambda dev=dev: halo_points(image, single, m, points, device=dev), args.repeats)
        print(f'halo test on {dev:6s}: {ms:6.2f} ms  ({int(halo[dev].sum())} halo points)')
    print(f'halo test: the same points on both: {np.array_equal(halo["cpu"], halo[args.device])}')
    rows, cols = np.nonzero(points)
    pick = seeded_subsample(len(rows), GUARD_SAMPLE, 0)
    rows, cols = rows[pick], cols[pick]
    residual = np.log(m[rows, cols].astype(np.float64)) - np.log(single[rows, cols].astype(np.float64))
    found = {dev: nearest_median(cols, rows, residual, 12.0, 16, dev) for dev in ('cpu', args.device)}
    for dev in ('cpu', args.device):
        ms = _median_ms(lambda dev=dev: nearest_median(cols, rows, residual, 12.0, 16, dev), args.repeats)
        print(f'guard neighbour search on {dev:6s}: {ms:6.2f} ms  ({len(rows)} points)')
    pairs = zip(found['cpu'], found[args.device], strict=True)
    same = all(np.array_equal(a, b, equal_nan=True) for a, b in pairs)
    print(f'guard neighbour search: the same numbers on both: {same}')


if __name__ == '__main__':
    main()
