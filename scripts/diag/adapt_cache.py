"""Diagnosis of the online adaptation (issue 14), step 1: cache each keyframe's multi-view
result, neighbours and ground truth once, so that adaptation variants can be compared in
minutes (scripts/diag/adapt_prequential.py).

    python scripts/diag/adapt_cache.py SEQ_DIR OUT.pkl FRAMES [RGB_CAMERA_YAML]
    PARAMS='{"multi_view": {"method": "filter"}}' ...   per-stage overrides (as --set)

Write OUT under an ignored folder (eval_out/): it holds data of the sequence.
"""

import json
import os
import pickle
import sys
import time

import depth_fusion_ros.evaluation.methods  # noqa register
from depth_fusion_ros.evaluation.context import EvalOptions, KeyframeContext
from depth_fusion_ros.evaluation.harness import load_evaluation_sequence
from depth_fusion_ros.evaluation.methods.multi_view import multi_view_result, neighbour_indices

path, out, frames = sys.argv[1], sys.argv[2], int(sys.argv[3])
rgbcam = sys.argv[4] if len(sys.argv) > 4 else None
params = json.loads(os.environ.get('PARAMS', '{}'))
opts = EvalOptions(frames=frames, rgb_cameras={'*': rgbcam} if rgbcam else {}, params=params)
seq = load_evaluation_sequence(path, opts)
shared = {}
rows = []
t0 = time.time()
for i in range(len(seq)):
    ctx = KeyframeContext(seq, i, opts, shared)
    mv = multi_view_result(ctx)
    rows.append(
        dict(
            i=i,
            rgb=ctx.frame.rgb,
            pose=ctx.frame.pose,
            depth=mv.depth,
            score=mv.score,
            nb=list(neighbour_indices(ctx)),
            gt=ctx.gt_depth,
        )
    )
    print(i, time.time() - t0, flush=True)
with open(out, 'wb') as fh:
    pickle.dump(dict(camera=seq.camera, rows=rows, name=seq.name), fh)
