"""Online adaptation on a CPU budget, as a live node lives it (issue 14, diagnostic).

``evaluate``'s ``single_view_adapted`` trains on every keyframe before the next one comes.
A live node on 2 cores cannot: keyframes come at ~6 a second, an update takes 0.5-2 s of
CPU, and the niced training thread gets what the other nodes leave (a small share of a core
during a 30 Hz stream). The node's training thread takes the oldest of the (two) keyframes
queued and the newest replaces the oldest when the queue is full (``adapt_queue_full``);
an update made while behind (another keyframe waiting, one dropped since the last one
taken, or the last update that trained slower than keyframes come; and the first update)
takes the adapter's ``steps_when_behind`` steps (the node's own rule,
``online.is_behind``). This replays that in
simulated time on a cache of scripts/diag/adapt_cache.py: keyframe k arrives at
``k * STRIDE / FPS``; an update lasts its measured CPU time (one torch thread) divided by
``SHARE``; keyframe k is predicted with the weights of the last update that finished before
it arrived. Prints the single-view MAE against the ground truth (read for the score only)
over all keyframes and over the second half, and the update counts:

    python scripts/diag/adapt_budget.py CACHE.pkl ['{"steps_when_behind": 6}']
    STRIDE=5 FPS=30 SHARE=0.7 QUEUE=2 ...   the defaults
"""

import json
import os
import pickle
import sys
import time

import cv2
import numpy as np
import torch

from depth_fusion_ros.adaptation.adapter import Adapter
from depth_fusion_ros.adaptation.config import AdaptConfig
from depth_fusion_ros.adaptation.online import is_behind
from depth_fusion_ros.adaptation.sample import Neighbour, make_sample
from depth_fusion_ros.metrics import upsample_depth, valid_mask

torch.set_num_threads(1)
STRIDE = int(os.environ.get('STRIDE', '5'))
FPS = float(os.environ.get('FPS', '30'))
SHARE = float(os.environ.get('SHARE', '0.7'))
QUEUE = int(os.environ.get('QUEUE', '2'))


def sample_of(rows: list, r: dict, cam, cfg: AdaptConfig):
    nb = [Neighbour(rows[j]['rgb'], rows[j]['pose']) for j in r['nb']]
    return make_sample(
        r['i'],
        r['rgb'],
        cam,
        r['depth'],
        r['score'],
        select_fraction=cfg.select_fraction,
        holdout_fraction=cfg.holdout_fraction,
        seed=cfg.seed,
        pose=r['pose'],
        neighbours=nb,
    )


def working_prediction(pred, rgb: np.ndarray, cam) -> np.ndarray:
    """The predictor's depth of ``rgb`` at the camera's (working) size."""
    d = pred.predict(rgb)
    if d.shape[::-1] != (cam.width, cam.height):
        d = cv2.resize(d, (cam.width, cam.height), interpolation=cv2.INTER_LINEAR)
    return d


def gt_errors(d: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """|depth - ground truth| where both are valid, ``d`` upsampled to the ground truth's
    size; also the upsampled depth and the mask."""
    p = upsample_depth(d.astype(np.float32), gt.shape[1], gt.shape[0])
    m = valid_mask(p, gt)
    return np.abs(p[m].astype(np.float64) - gt[m]), p, m


def abs_errors(pred, r: dict, cam) -> np.ndarray:
    return gt_errors(working_prediction(pred, r['rgb'], cam), r['gt'])[0]


def main() -> None:
    with open(sys.argv[1], 'rb') as fh:
        data = pickle.load(fh)
    over = json.loads(sys.argv[2]) if len(sys.argv) > 2 else {}
    cam, rows = data['camera'], data['rows']
    keys = rows[::STRIDE]
    cfg = AdaptConfig.from_dict(over)
    ad = Adapter.from_spec('default', cfg)
    freeze = os.environ.get('FREEZE', '')
    for name in filter(None, freeze.split(',')):
        for prm in getattr(ad.net, name).parameters():
            prm.requires_grad_(False)
    ad.warm_up()
    effective = [(0.0, ad.predictor())]  # (time the weights take effect, predictor)
    t_free, queue, updates, cpu_total, dropped, dropped_at_take = 0.0, [], 0, 0.0, 0, 0
    errors, log_updates = [], []
    last_wall = None
    for k, r in enumerate(keys):
        t_k = k * STRIDE / FPS
        while queue and max(t_free, queue[0][0]) <= t_k:
            arrival, row = queue.pop(0)  # the node's queue: oldest first
            start = max(t_free, arrival)
            behind = is_behind(bool(queue), dropped > dropped_at_take, last_wall, STRIDE / FPS)
            dropped_at_take = dropped
            c0 = time.process_time()
            rep = ad.observe(sample_of(rows, row, cam, cfg), behind=behind)
            g = rep.guard
            guard = (g.before, g.after) if g else (None, None)
            log_updates.append((k, row['i'], rep.status, rep.reason, *guard))
            cpu = time.process_time() - c0
            cpu_total += cpu
            t_free = start + cpu / SHARE
            if rep.status != 'skipped':
                last_wall = cpu / SHARE
            updates += 1
            effective.append((t_free, ad.predictor()))
        pred = [p for t, p in effective if t <= t_k][-1]
        e = abs_errors(pred, r, cam)
        errors.append((e.sum(), e.size))
        queue.append((t_k, r))
        if len(queue) > QUEUE:
            queue.pop(0)
            dropped += 1
    if os.environ.get('DUMP'):
        with open(os.environ['DUMP'], 'w') as fh:
            json.dump(dict(mae=[a / max(b, 1) for a, b in errors], updates=log_updates), fh)
    half = len(errors) // 2
    mae = sum(s for s, _ in errors) / sum(n for _, n in errors)
    mae2 = sum(s for s, _ in errors[half:]) / sum(n for _, n in errors[half:])
    print(
        json.dumps(
            dict(
                cache=os.path.basename(sys.argv[1]),
                over=over,
                share=SHARE,
                keyframes=len(keys),
                updates=updates,
                behind_updates=ad.counters.behind,
                cpu_per_update_s=round(cpu_total / max(updates, 1), 3),
                mae=round(mae, 4),
                mae_second_half=round(mae2, 4),
            )
        )
    )


if __name__ == '__main__':
    main()
