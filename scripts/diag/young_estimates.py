"""The filter's published estimates per keyframe against the ground truth (figures, no assertions).

    python scripts/diag/young_estimates.py TUM_DIR [filter.FIELD=VALUE ...]

Runs ``DepthFilter`` over the first 60 frames of a TUM-layout folder at 320x240 and, every
fifth frame, prints the share of the published estimates more than 10 % off the ground truth
and the good density (estimates within 10 %, of all pixels). What docs/multi_view.md, "Young
estimates on a keyframe stream", measured with ``depth-fusion synth /tmp/st_keyframes
--stress keyframes --frames 150 --seed 5``: 11-27 % off per keyframe with
``fill_min_updates=1`` (before 2026-11-29), 6-11 % with the default 3.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from depth_fusion_ros.data.tum import load_tum_sequence
from depth_fusion_ros.multiview.filter import DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig


def main(path: str, overrides: list[str]) -> None:
    seq = load_tum_sequence(path, width=320, height=240, max_frames=60)
    defaults = FilterConfig()
    fields = {}
    for item in overrides:
        name, value = item.removeprefix('filter.').split('=')
        fields[name] = type(getattr(defaults, name))(value)
    f = DepthFilter(seq.camera, dataclasses.replace(defaults, **fields))
    bad, good = [], []
    for i, frame in enumerate(seq.frames):
        f.process(frame.gray, frame.pose)
        if i % 5 or i == 0:
            continue
        result, gt = f.result(frame.pose), seq.gt_depth_working(i)
        ok = np.isfinite(result.depth) & np.isfinite(gt) & (gt > 0)
        error = np.abs(result.depth - gt) / gt
        bad.append(float(np.mean(error[ok] > 0.1)) if ok.any() else float('nan'))
        good.append(float((ok & (error <= 0.1)).mean()))
    print(
        f'{fields or "defaults"}: > 10 % off per keyframe {" ".join(f"{b:.2f}" for b in bad)}; '
        f'good density {np.mean(good):.3f}'
    )


if __name__ == '__main__':
    main(sys.argv[1], sys.argv[2:])
