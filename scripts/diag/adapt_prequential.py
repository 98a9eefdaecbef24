"""Diagnosis of the online adaptation (issue 14), step 2: the prequential loop of
``evaluate``'s ``single_view_adapted`` (predict keyframe k, then ``observe`` it) on a cache of
scripts/diag/adapt_cache.py, printing per keyframe the MAE against the ground truth, the
guard's before/after, its paired per-point change and standard error, and the error at and
away from the selected multi-view points. The ground truth is read for these figures only;
the adapter never sees it, except in the oracle runs, which replace its training targets:

    python scripts/diag/adapt_prequential.py CACHE.pkl OUT.json '{"guard_tolerance": 1e9}'
    MAXF=40 ...        only the first 40 keyframes (all frames stay available as neighbours)
    ORACLE=sel ...     exact depth at the selected multi-view points instead of theirs
    ORACLE=1 ...       exact depth at every other pixel (what dense supervision could give)

One torch thread, CPU.
"""

import json
import os
import pickle
import sys
import time

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from depth_fusion_ros.adaptation.adapter import Adapter
from depth_fusion_ros.adaptation.config import AdaptConfig
from depth_fusion_ros.adaptation.sample import Neighbour, make_sample

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from adapt_budget import gt_errors, working_prediction  # scripts/diag is no package

torch.set_num_threads(1)
cache, out = sys.argv[1], sys.argv[2]
over = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
with open(cache, 'rb') as fh:
    data = pickle.load(fh)

cam, rows = data['camera'], data['rows']
MAXF = int(os.environ.get('MAXF', '1000'))
cfg = AdaptConfig.from_dict(over)
ad = Adapter.from_spec('default', cfg)
calls = []
orig = Adapter._guard


def guard(self, samples):
    v = orig(self, samples)
    usable = [s for s in samples if s.n_holdout > 0]
    with torch.no_grad():
        res = []
        for s in usable:
            ld = self._eval_forward(s.x)
            p = F.grid_sample(
                ld, s.holdout_grid[None, None], mode='bilinear', padding_mode='border', align_corners=False
            ).reshape(-1)
            res.append((p - s.holdout_log).numpy().copy())
    calls.append(res)
    return v


Adapter._guard = guard
pred = ad.predictor()
ver = 0
sum_abs = n = 0
recs = []
t0 = time.time()
for r in rows[:MAXF]:
    d = working_prediction(pred, r['rgb'], cam)
    gt = r['gt']
    e, p, m = gt_errors(d, gt)
    sum_abs += e.sum()
    n += e.size
    # gt log error for the network on this frame (scale)
    lr = np.median(np.log(p[m]) - np.log(gt[m]))
    mae_scaled = float(np.abs(p[m] * np.exp(-lr) - gt[m]).mean())
    nb = [Neighbour(rows[j]['rgb'], rows[j]['pose']) for j in r['nb']]
    mvd, mvs, sf = r['depth'], r['score'], cfg.select_fraction
    if os.environ.get('ORACLE') == 'sel':
        g0 = cv2.resize(r['gt'], (cam.width, cam.height), interpolation=cv2.INTER_NEAREST).astype(np.float32)
        mvd = np.where(np.isfinite(mvd) & (g0 > 0), g0, np.nan).astype(np.float32)
    elif os.environ.get('ORACLE'):
        g0 = cv2.resize(r['gt'], (cam.width, cam.height), interpolation=cv2.INTER_NEAREST).astype(np.float32)
        mvd = np.where(g0 > 0, g0, np.nan).astype(np.float32)
        mvd[1::2, :] = np.nan
        mvd[:, 1::2] = np.nan
        mvs = np.where(np.isfinite(mvd), 1.0, np.nan).astype(np.float32)
        sf = 1.0
    s = make_sample(
        r['i'],
        r['rgb'],
        cam,
        mvd,
        mvs,
        select_fraction=sf,
        holdout_fraction=cfg.holdout_fraction,
        seed=cfg.seed,
        pose=r['pose'],
        neighbours=nb,
    )
    # multi-view point quality vs GT (diagnostic only, never used for training)
    gw = cv2.resize(gt, (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
    uv = np.concatenate([s.train_uv, s.holdout_uv]).astype(int)
    zz = np.concatenate([s.train_depth, s.holdout_depth])
    g = gw[uv[:, 1], uv[:, 0]]
    ok = g > 0
    mv_err = float(np.median(np.abs(np.log(zz[ok]) - np.log(g[ok])))) if ok.any() else float('nan')
    mv_bias = float(np.median(np.log(zz[ok]) - np.log(g[ok]))) if ok.any() else float('nan')
    dw = cv2.resize(d, (cam.width, cam.height)) if d.shape[::-1] != (cam.width, cam.height) else d
    sel = np.zeros(gw.shape, bool)
    sel[uv[:, 1], uv[:, 0]] = True
    okg = gw > 0
    ae = np.abs(dw - gw)
    err_sel = float(ae[sel & okg].mean())
    err_rest = float(ae[~sel & okg].mean())
    calls.clear()
    rep = ad.observe(s)
    if ad.version != ver:
        pred = ad.predictor()
        ver = ad.version
    rec = dict(
        i=r['i'],
        mae=float(e.mean()),
        mae_scaled=mae_scaled,
        med_logratio=float(lr),
        status=rep.status,
        n_train=len(s.train_depth),
        n_hold=len(s.holdout_depth),
        mv_med_abslog=mv_err,
        mv_bias=mv_bias,
        err_sel=err_sel,
        err_rest=err_rest,
        sel_frac=float((sel & okg).sum() / okg.sum()),
        loss0=rep.loss_first,
        loss1=rep.loss_last,
    )
    if rep.guard is not None and len(calls) == 2:
        b, a = calls
        rec['before'] = rep.guard.before
        rec['after'] = rep.guard.after
        # per keyframe mean abs, and paired per-point diff stats
        kb = [float(np.abs(x).mean()) for x in b]
        ka = [float(np.abs(x).mean()) for x in a]
        rec['kf_before'] = kb
        rec['kf_after'] = ka
        diffs = [np.abs(y) - np.abs(x) for x, y in zip(b, a, strict=True)]
        # SE of the mean-over-keyframes of the mean per keyframe diff
        se = np.sqrt(sum(dd.var(ddof=1) / dd.size for dd in diffs if dd.size > 1)) / len(diffs)
        rec['delta'] = float(np.mean([dd.mean() for dd in diffs]))
        rec['se'] = float(se)
        rec['n_pts'] = [int(dd.size) for dd in diffs]
        rec['sd_abs_before'] = [float(np.abs(x).std()) for x in b]
        rec['med_res_new_before'] = float(np.median(b[0]))
    recs.append(rec)
    print(
        json.dumps(
            {
                k: (round(v, 4) if isinstance(v, float) else v)
                for k, v in rec.items()
                if k
                in (
                    'mae_scaled',
                    'err_sel',
                    'err_rest',
                    'sel_frac',
                    'i',
                    'mae',
                    'status',
                    'before',
                    'after',
                    'delta',
                    'se',
                    'med_logratio',
                    'mv_bias',
                    'med_res_new_before',
                )
            }
        ),
        flush=True,
    )
res = dict(mae=sum_abs / n, counters=ad.counters.as_dict(), recs=recs, over=over, seconds=time.time() - t0)
with open(out, 'w') as fh:
    json.dump(res, fh)
print('MAE', sum_abs / n, ad.counters.as_dict())
