"""The temporal inverse-depth filter (multi_view.method: filter) on synthetic rooms."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from jumped_views import jumped_views

import depth_fusion_ros.multiview.filter as filter_module
from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.metrics import good_density
from depth_fusion_ros.multiview.filter import KEYFRAME, SKIPPED, UPDATED, DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.filter_stream import FilterStream
from depth_fusion_ros.multiview.filter_update import BetaGaussian, gaussian_uniform_update, outlier_vote
from depth_fusion_ros.multiview.neighbours import select_neighbours
from depth_fusion_ros.multiview.semidense import estimate_semidense, select_best_fraction

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _abs_rel(depth: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    valid = np.isfinite(depth) & np.isfinite(gt) & (gt > 0)
    if mask is not None:
        valid &= mask
    return np.abs(depth[valid] - gt[valid]) / gt[valid]


@pytest.fixture(scope='module')
def filtered(synthetic_sequence):
    """The filter run over the whole high-parallax sequence, and its result in the last frame."""
    seq = synthetic_sequence
    f = DepthFilter(seq.camera)
    actions = [f.process(fr.gray, fr.pose) for fr in seq.frames]
    return f, actions, f.result(seq.frames[-1].pose)


def test_filter_converges_to_the_true_depth_better_than_the_sweep(synthetic_sequence, filtered):
    seq = synthetic_sequence
    f, actions, result = filtered
    last = len(seq) - 1
    gt = seq.gt_depth_working(last)
    assert actions[0] == KEYFRAME and UPDATED in actions
    assert f.stats.frames == len(seq) and f.stats.updated + f.stats.skipped + f.stats.keyframes == len(seq)
    rel = _abs_rel(result.depth, gt)
    assert result.density > 0.1, result.density
    assert np.median(rel) < 0.03, np.median(rel)
    # The sweep on the same frame (online neighbours: the past, as the filter) at equal density:
    # the filter's best estimates by score, as many as the sweep has, are more accurate.
    chosen = select_neighbours(seq.poses, last, 4, 'online', seq.camera)
    sweep = estimate_semidense(
        seq.frames[last].gray,
        seq.frames[last].pose,
        [seq.frames[i].gray for i in chosen],
        [seq.frames[i].pose for i in chosen],
        seq.camera,
    )
    n = int(sweep.valid.sum())
    assert result.valid.sum() >= n
    best = np.zeros(result.depth.shape, bool)
    flat = np.flatnonzero(result.valid)
    best.ravel()[flat[np.argsort(-result.score.ravel()[flat])[:n]]] = True
    filter_error = np.mean(_abs_rel(result.depth, gt, best))
    sweep_error = np.mean(_abs_rel(sweep.depth, gt))
    assert filter_error < sweep_error, (filter_error, sweep_error)
    # Its own fields: variance, inlier ratio and update counts where there is an estimate.
    assert np.array_equal(np.isfinite(result.variance), result.valid)
    assert np.nanmin(result.inlier_ratio) >= FilterConfig().publish_inlier_ratio
    assert np.nanmin(result.updates) >= FilterConfig().min_updates
    # Selection works unchanged on it.
    assert select_best_fraction(result, 0.25).sum() == round(0.25 * result.valid.sum())


def _median_selected_abs_rel(result, gt) -> float:
    return float(np.median(_abs_rel(result.depth, gt, select_best_fraction(result, 0.25))))


def test_filter_has_twice_the_sweeps_good_density_at_better_selected_accuracy(synthetic_sequence, filtered):
    """Issue 11's density target on the synthetic room, both causal (the sweep's online
    neighbours, the filter after the stream): pixels within 10 % of the truth, of all pixels."""
    seq = synthetic_sequence
    _, _, result = filtered
    last = len(seq) - 1
    gt = seq.gt_depth_working(last)
    chosen = select_neighbours(seq.poses, last, 4, 'online', seq.camera)
    fr = seq.frames
    sweep = estimate_semidense(
        fr[last].gray, fr[last].pose, [fr[i].gray for i in chosen], [fr[i].pose for i in chosen], seq.camera
    )
    filter_good, sweep_good = good_density(result.depth, gt), good_density(sweep.depth, gt)
    assert filter_good > 0.18 and filter_good >= 2.0 * sweep_good, (filter_good, sweep_good)
    assert _median_selected_abs_rel(result, gt) <= _median_selected_abs_rel(sweep, gt)


def test_evaluation_reports_the_filters_good_density_above_the_sweeps(synthetic_sequence):
    """``--set multi_view.method=filter`` through the harness: the report's good density."""
    from depth_fusion_ros.evaluation.context import EvalOptions
    from depth_fusion_ros.evaluation.harness import evaluate_sequence

    good = {}
    for method in ('sweep', 'filter'):
        options = EvalOptions(frames=24, stride=12, params={'multi_view': {'method': method}})
        result = evaluate_sequence(synthetic_sequence, ['multi_view'], options, show_progress=False)
        good[method] = result.records['multi_view'].to_json()['good_density']
    assert good['filter'] > 1.5 * good['sweep'], good


def test_good_density_counts_only_accurate_estimates():
    gt = np.full((2, 4), 2.0, np.float32)
    gt[1, 3] = np.nan  # no ground truth: never good
    pred = np.array([[2.1, 2.5, np.nan, 1.85], [2.0, 2.19, 1.0, 2.0]], np.float32)
    assert good_density(pred, gt) == 4 / 8  # 2.1, 1.85, 2.0, 2.19 are within 10 %


def test_new_keyframe_pixels_get_a_prior_from_carried_neighbours(synthetic_sequence):
    """LSD-SLAM's hole filling: right after a keyframe switch, pixels between carried
    estimates hold an accurate prior (a short search next frame, not a whole-range one)."""
    seq = synthetic_sequence
    priors = {}
    for radius in (0, FilterConfig().fill_radius):
        # Whole-range seeding (seed_radius=0): with the neighbours' bracket the pixels that only
        # filling reaches are those whose bracketed first search failed (a harder subset).
        f = DepthFilter(seq.camera, FilterConfig(fill_radius=radius, seed_radius=0))
        i = 0
        while f.stats.keyframes < 2:
            f.process(seq.frames[i].gray, seq.frames[i].pose)
            i += 1
        key = f.key
        priors[radius] = key.prior.clone()
    gt = seq.gt_depth_working(i - 1).ravel()[key.flat.numpy()]
    filled = (priors[FilterConfig().fill_radius] & ~priors[0]).numpy()
    assert filled.sum() > 0.05 * key.flat.numel(), filled.sum()
    # The pixels only filling gives a prior (the whole-range search found nothing there),
    # after one short search against the previous keyframe: mostly right, a prior to refine.
    depth = 1.0 / key.state.mu.numpy()[filled]
    rel = np.abs(depth - gt[filled]) / gt[filled]
    assert np.median(rel) < 0.08 and np.mean(rel < 0.1) > 0.55, (np.median(rel), np.mean(rel < 0.1))


def _stripes(camera: PinholeCamera) -> np.ndarray:
    """Horizontal stripes: all the gradient is vertical."""
    rows = np.arange(camera.height, dtype=np.float32)[:, None]
    return np.repeat(0.5 + 0.4 * np.sin(rows * 0.7), camera.width, axis=1)


def test_edges_along_the_epipolar_line_are_not_searched():
    """Sideways motion: every epipolar line is horizontal, along the stripes. Every position
    on the line matches equally well, so LSD-SLAM's test leaves such pixels alone."""
    camera = PinholeCamera(80, 60, 60.0, 60.0, 39.5, 29.5)
    image = _stripes(camera)
    attempts = {}
    for threshold in (0.0, FilterConfig().min_epipolar_gradient):
        f = DepthFilter(camera, FilterConfig(min_epipolar_gradient=threshold))
        for k in range(6):
            pose = np.eye(4)
            pose[0, 3] = 0.05 * k  # 5 cm sideways per frame
            f.process(image, pose)
        assert f.key.flat.numel() > 0  # the stripes are candidates
        attempts[threshold] = int(f.key.attempts.sum())
    assert attempts[0.0] > 0
    assert attempts[FilterConfig().min_epipolar_gradient] == 0


def _striped_wall(camera: PinholeCamera, x: float, depth: float, period_px: float) -> np.ndarray:
    """A fronto-parallel wall ``depth`` m away, seen from ``x`` m along it: wavy near-vertical
    stripes ``period_px`` pixels apart, their contrast varying slowly (rendered exactly: the
    same wall point has the same grey in every frame)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    X = x + (u - camera.cx) * depth / camera.fx
    Y = (v - camera.cy) * depth / camera.fy
    phase = 2 * np.pi * X / (period_px * depth / camera.fx) + 0.8 * np.sin(2 * np.pi * Y / 0.4)
    contrast = 0.25 + 0.1 * np.sin(2 * np.pi * X / 0.53) + 0.05 * np.sin(2 * np.pi * Y / 0.23)
    return (0.5 + contrast * np.tanh(2.5 * np.sin(phase))).astype(np.float32)


def test_a_texture_that_repeats_along_the_line_gives_no_estimates_rather_than_wrong_ones():
    """``filter.first_check_px``: stripes 3 px apart, crossed by every epipolar line (sideways
    motion). The whole-range search's coarse samples land on a neighbouring stripe, and the
    short searches around it find a stripe in every frame: unchecked, every published estimate
    is wrong, about a third of the wall's depth. Checked at one sample a pixel, no first
    measurement is distinct, and nothing is published."""
    camera = PinholeCamera(160, 120, 120.0, 120.0, 79.5, 59.5)
    depth = 3.0
    published = {}
    for check in (0.0, FilterConfig().first_check_px):
        f = DepthFilter(camera, FilterConfig(first_check_px=check))
        for k in range(20):
            pose = np.eye(4)
            pose[0, 3] = 0.02 * k  # 2 cm sideways a frame, 0.8 px of the stripes
            f.process(_striped_wall(camera, pose[0, 3], depth, 3.0), pose)
        d = f.result(pose).depth
        published[check] = d[np.isfinite(d) & (d > 0)]
    unchecked, checked = published[0.0], published[FilterConfig().first_check_px]
    assert unchecked.size > 500 and (np.abs(unchecked / depth - 1) > 0.2).mean() > 0.9
    assert (np.abs(checked / depth - 1) > 0.2).sum() <= 0.02 * unchecked.size


def test_converged_pixels_are_left_alone(synthetic_sequence, monkeypatch):
    """REMODE: a frame that cannot shrink a pixel's variance does not search it."""
    seq = synthetic_sequence
    searched = {}
    real = filter_module.search_interval
    for information in (0.0, 1.0):
        rows = []

        def counting(key_desc, *args, rows=rows, **kwargs):
            rows.append(key_desc.shape[1])
            return real(key_desc, *args, **kwargs)

        monkeypatch.setattr(filter_module, 'search_interval', counting)
        # Exact poses, told as they are: a refined pose moves each frame a little, and the
        # estimates it met would be searched again for that reason, not for their variance.
        f = DepthFilter(seq.camera, FilterConfig(min_information=information, refine_poses=False))
        for fr in seq.frames[:8]:
            f.process(fr.gray, fr.pose)
        searched[information] = sum(rows)
    assert searched[1.0] < 0.8 * searched[0.0], searched


def test_variance_shrinks_with_frames(synthetic_sequence):
    seq = synthetic_sequence
    f = DepthFilter(
        seq.camera, FilterConfig(keyframe_parallax=10.0, keyframe_rotation_deg=90.0, keyframe_min_visible=0.0)
    )
    medians = []
    for i, fr in enumerate(seq.frames[:12]):
        f.process(fr.gray, fr.pose)
        if i in (4, 11):
            r = f.result()
            medians.append((np.nanmedian(np.sqrt(r.variance) * r.depth), np.nanmedian(r.updates)))
    assert f.stats.keyframes == 1
    (early_sigma, early_n), (late_sigma, late_n) = medians
    assert late_n > early_n
    assert late_sigma < 0.7 * early_sigma, medians


def test_estimates_are_propagated_into_the_next_keyframe(synthetic_sequence):
    seq = synthetic_sequence
    f = DepthFilter(seq.camera)
    i = 0
    while f.stats.keyframes < 2:
        f.process(seq.frames[i].gray, seq.frames[i].pose)
        i += 1
    key = i - 1
    # The new keyframe holds estimates with several measurements: only propagation brings them.
    carried = f.key.updates >= 3
    assert int(carried.sum()) > 0.05 * f.key.flat.numel()
    r = f.result()
    gt = seq.gt_depth_working(key)
    many = np.nan_to_num(r.updates) >= 3
    assert many.sum() > 500
    assert np.median(_abs_rel(r.depth, gt, many)) < 0.03


def test_the_streams_first_keyframe_asks_one_measurement_more(synthetic_sequence):
    """In the first keyframe nothing is carried: an estimate is published after
    ``first_keyframe_min_updates`` measurements; a later keyframe keeps ``min_updates``."""
    seq = synthetic_sequence
    f = DepthFilter(seq.camera)
    i = 0
    while f.stats.updated < 2:  # two measuring frames: estimates with 2 measurements at most
        f.process(seq.frames[i].gray, seq.frames[i].pose)
        i += 1
    assert f.key.first and int((f.key.updates >= 2).sum()) > 0
    updates = np.nan_to_num(f.result().updates)
    assert (f.result().density == 0.0) or updates[updates > 0].min() >= 3
    off = DepthFilter(seq.camera, FilterConfig(first_keyframe_min_updates=1))
    for fr in seq.frames[:i]:
        off.process(fr.gray, fr.pose)
    assert np.nanmin(off.result().updates) == 2
    while f.stats.keyframes < 2:
        f.process(seq.frames[i].gray, seq.frames[i].pose)
        i += 1
    assert not f.key.first  # estimates were carried into it
    assert np.nanmin(f.result().updates) < FilterConfig().first_keyframe_min_updates


def test_a_jump_sends_the_carried_estimates_to_be_confirmed_again(synthetic_sequence):
    """A keyframe turned further than ``max_rotation_deg`` from the last (a relocalisation, a
    gap in the stream) gets the old estimates by geometry alone, and those hidden in the new
    view land on it all the same. So they come as priors with no measurement: nothing is
    published at the jump, and no first measurement is taken from the old keyframe image
    (too turned to match); two measuring frames from the new place publish them again,
    accurate. Before, the carried counts were published at once (the ``keyframes`` stress
    stream, which jumped 60 deg every 20 frames, fused three keyframes 8-13 % above their
    single-view input)."""
    seq = synthetic_sequence
    f = DepthFilter(seq.camera)
    for fr in seq.frames[:12]:
        f.process(fr.gray, fr.pose)
    assert f.result().density > 0.05 and f.stats.jumps == 0
    jump, *after = jumped_views(seq, 11, 40.0, (0.05, 0.10))
    assert f.process(jump.gray, jump.pose) == KEYFRAME and f.stats.jumps == 1
    assert bool(f.key.prior.any()) and int(f.key.updates.max()) == 0  # carried, to confirm
    assert f.result().density == 0.0
    for fr in after:
        assert f.process(fr.gray, fr.pose) == UPDATED
    r = f.result(after[-1].pose)
    assert r.density > 0.02 and f.stats.jumps == 1
    assert np.median(_abs_rel(r.depth, after[-1].depth)) < 0.05


def test_outliers_lower_the_inlier_ratio():
    mu, var = torch.tensor([0.5, 0.5]), torch.tensor([1e-4, 1e-4])
    prior = BetaGaussian(mu, var, torch.tensor([10.0, 10.0]), torch.tensor([10.0, 10.0]))
    tau2 = torch.tensor([1e-4, 1e-4])
    state = prior
    for _ in range(5):  # pixel 0 keeps agreeing, pixel 1 gets far-off measurements
        state = gaussian_uniform_update(state, torch.tensor([0.5, 2.0]), tau2, (0.1, 5.0))
    assert state.inlier_ratio[0] > 0.55 > 0.45 > state.inlier_ratio[1]
    assert abs(float(state.mu[1]) - 0.5) < 0.05  # the outliers barely moved the estimate
    assert float(state.var[0]) < 1e-4 / 4
    failed = outlier_vote(prior, torch.tensor([False, True]))
    assert failed.inlier_ratio[1] < failed.inlier_ratio[0]


def test_occluding_outliers_are_dropped_in_the_filter(synthetic_sequence):
    """Frames whose image is another scene (a wrong frame in the stream) give outlier votes."""
    seq = synthetic_sequence
    config = FilterConfig(keyframe_parallax=10.0, keyframe_rotation_deg=90.0, keyframe_min_visible=0.0)
    f = DepthFilter(seq.camera, config)
    for fr in seq.frames[:8]:
        f.process(fr.gray, fr.pose)
    before = f.key.state.inlier_ratio[f.key.updates > 0].mean()
    rng = np.random.default_rng(0)
    for fr in seq.frames[8:12]:
        f.process(rng.random(fr.gray.shape).astype(np.float32), fr.pose)  # noise instead of the room
    after = f.key.state.inlier_ratio[f.key.updates > 0].mean()
    assert after < before - 0.05, (before, after)


def test_edge_minima_are_outlier_votes_not_confirmations(synthetic_sequence):
    """``reject_edge_minima``: a short search whose best sample is its interval's end is an
    outlier vote, not a measurement. Counted as one (the old behaviour), a wrong estimate
    confirmed itself at its interval's edge frame after frame (on TUM fr1_xyz its first
    frames' estimates were 20-40 % too close). On the synthetic room it leaves fewer estimates
    more than 10 % off, and its tail shorter, for about as many accurate ones."""
    seq = synthetic_sequence
    errors = {}
    for reject in (True, False):
        f = DepthFilter(seq.camera, FilterConfig(reject_edge_minima=reject))
        per_frame = []
        for i, fr in enumerate(seq.frames):
            f.process(fr.gray, fr.pose)
            if i >= 6:
                gt = seq.gt_depth_working(i)
                per_frame.append(_abs_rel(f.result(fr.pose).depth, gt))
        errors[reject] = np.concatenate(per_frame)
    new, old = errors[True], errors[False]
    assert (new > 0.1).mean() < 0.92 * (old > 0.1).mean(), ((new > 0.1).mean(), (old > 0.1).mean())
    assert np.quantile(new, 0.9) < 0.85 * np.quantile(old, 0.9), (
        np.quantile(new, 0.9),
        np.quantile(old, 0.9),
    )
    assert (new <= 0.1).sum() > 0.95 * (old <= 0.1).sum()


def test_a_noise_selected_sliver_is_not_published(synthetic_sequence):
    """Rotation-heavy motion at 160x120, 7 frames: few estimates reach the precision test,
    and those that do are the ones their noise made too near (the test divides by their own
    mu). With ``min_published_fraction`` 0 that sliver is published, biased together; by
    default nothing is. On the high-parallax room the rule changes nothing."""
    from depth_fusion_ros.data.synthetic import render_sequence, stress_config

    seq = render_sequence(stress_config('rotation', width=160, height=120, frames=7, seed=0))
    published = {}
    for fraction in (0.0, FilterConfig().min_published_fraction):
        f = DepthFilter(seq.camera, FilterConfig(min_published_fraction=fraction))
        for fr in seq.frames:
            f.process(fr.gray, fr.pose)
        assert f.stats.keyframes == 1
        measured = (f.key.updates >= 2).sum()
        published[fraction] = f.result()
    sliver = published[0.0]
    valid = np.isfinite(sliver.depth)
    assert 0 < valid.sum() < 0.05 * int(measured)
    gt = seq.gt_depth_working(0)
    signed = (sliver.depth[valid] - gt[valid]) / gt[valid]
    assert np.median(signed) < -0.1  # too near, together
    assert published[FilterConfig().min_published_fraction].density == 0.0
    # and says so (multi_view_node notes it as filter_minority)
    share = published[FilterConfig().min_published_fraction].withheld_fraction
    assert share is not None and 0 < share < FilterConfig().min_published_fraction
    assert published[0.0].withheld_fraction is None
    default = FilterConfig().min_published_fraction
    for fraction in (0.0, default):
        f = DepthFilter(synthetic_sequence.camera, FilterConfig(min_published_fraction=fraction))
        for fr in synthetic_sequence.frames[:10]:
            f.process(fr.gray, fr.pose)
        published[('room', fraction)] = f.result().density
    assert published[('room', 0.0)] == published[('room', default)] > 0.1
    assert f.result().withheld_fraction is None


def _keyframe_of(us: np.ndarray, vs: np.ndarray, rho: np.ndarray, sigma: np.ndarray) -> SimpleNamespace:
    """A filter keyframe's published-state fields: every estimate measured 5 times, inliers."""
    n = len(us)
    state = BetaGaussian(
        torch.as_tensor(rho, dtype=torch.float32),
        torch.as_tensor(sigma, dtype=torch.float32) ** 2,
        torch.full((n,), 20.0),
        torch.full((n,), 2.0),
    )
    return SimpleNamespace(
        state=state,
        updates=torch.full((n,), 5),
        first=False,
        us=torch.as_tensor(us, dtype=torch.float32),
        vs=torch.as_tensor(vs, dtype=torch.float32),
    )


def test_a_regions_noise_selected_sliver_is_not_published(synthetic_sequence):
    """The minority test per region (``published_fraction_cells``): a near region (right half)
    whose estimates all pass the precision test lifts the keyframe's share above
    ``min_published_fraction`` while in the far region (left half) only 2 % pass, the tail
    its noise made too near (a live synthetic room's first published keyframe: 40 of 3854
    passed on the far wall's corner, all 2-4x too near, and the fusion bent the wall to 0.6x).
    That sliver is withheld; the near region, and a far region where most pass, are not."""
    cam = synthetic_sequence.camera
    rng = np.random.default_rng(0)
    n = 4000
    us = rng.integers(0, cam.width, n)
    vs = rng.integers(0, cam.height, n)
    left = us < cam.width // 2
    rho = np.where(left, 0.25, 1.0)  # far wall 4 m, near object 1 m
    sigma = np.where(left, 0.05, 0.02)  # relative 0.2 on the wall: fails max_relative_sigma 0.1
    tail = left & (rng.random(n) < 0.02)
    rho = np.where(tail, 0.8, rho)  # the sliver: 3x too near, and passes (0.05 / 0.8 < 0.1)
    key = _keyframe_of(us, vs, rho, sigma)
    published = {}
    for cells in (0, FilterConfig().published_fraction_cells):
        f = DepthFilter(cam, FilterConfig(published_fraction_cells=cells))
        mask, withheld = f._published(key)
        assert withheld is None  # over the keyframe, 51 % pass: the keyframe-wide test is happy
        published[cells] = mask.numpy()
    assert published[0][tail].all() and published[0][~left].all()
    default = published[FilterConfig().published_fraction_cells]
    assert not default[tail].any()
    assert default[~left].all()
    # a far region where most estimates pass keeps its estimates, the too-near few included
    sigma_ok = np.where(left, 0.01, 0.02)
    default_ok = DepthFilter(cam)._published(_keyframe_of(us, vs, rho, sigma_ok))[0].numpy()
    assert default_ok.all()
    with pytest.raises(ValueError, match='published_fraction_cells'):
        FilterConfig(published_fraction_cells=-1).validate()


def test_the_far_walls_sliver_is_withheld_on_a_live_rooms_first_published_keyframe():
    """The case that showed the cell rule was needed: the synthetic room of a 600-frame live
    stream (seed 5, rendered 640x480, filtered at 320x240 as the node does), its first 36
    frames. At frame 35 the filter publishes its first keyframe; 46 % of its measured
    estimates pass, but on the far wall only 1 %, nearly all 2-4x too near. Without the cell
    rule 143 estimates in the image's top third are more than 30 % off; with it about a
    quarter of those, for 99 % of the accurate ones (the test asks for 97 %)."""
    import itertools

    import cv2

    from depth_fusion_ros.data.synthetic.config import SynthConfig
    from depth_fusion_ros.data.synthetic.world import build_world, iter_frames

    cfg = SynthConfig(frames=600, seed=5)
    scene, trajectory = build_world(cfg)
    frames = list(itertools.islice(iter_frames(cfg, scene, trajectory), 36))
    camera = cfg.camera().scaled(320, 240)

    def grey(rgb: np.ndarray) -> np.ndarray:
        return cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (320, 240), interpolation=cv2.INTER_AREA)

    gt = cv2.resize(frames[0][1].depth, (320, 240), interpolation=cv2.INTER_NEAREST)
    counts = {}
    for cells in (0, FilterConfig().published_fraction_cells):
        f = DepthFilter(camera, FilterConfig(published_fraction_cells=cells))
        for _, frame, pose in frames:
            f.process(grey(frame.rgb), pose)
        assert f.stats.keyframes == 1
        depth = f.result().depth
        valid = np.isfinite(depth)
        error = np.full(depth.shape, np.nan)
        error[valid] = np.abs(np.log(depth[valid] / gt[valid]))
        top = error[:80]
        counts[cells] = (int((top > 0.3).sum()), int((error <= 0.1).sum()))
    (bad_off, good_off), (bad_on, good_on) = counts[0], counts[FilterConfig().published_fraction_cells]
    assert bad_off > 100, counts
    assert bad_on < 0.4 * bad_off, counts
    assert good_on > 0.97 * good_off, counts


def test_frames_without_baseline_are_skipped(synthetic_sequence):
    seq = synthetic_sequence
    f = DepthFilter(seq.camera)
    assert f.process(seq.frames[0].gray, seq.frames[0].pose) == KEYFRAME
    assert f.process(seq.frames[0].gray, seq.frames[0].pose) == SKIPPED
    assert f.result().density == 0.0


def test_stream_restarts_when_asked_for_an_earlier_frame(synthetic_sequence):
    seq = synthetic_sequence
    calls = []

    def frame(i):
        calls.append(i)
        return seq.frames[i].gray, seq.frames[i].pose

    stream = FilterStream(frame, seq.camera)
    stream.result_at(3)
    stream.result_at(5)
    assert calls == [0, 1, 2, 3, 3, 4, 5, 5]  # each frame fed once, in order (+ the pose asked for)
    assert stream.next_index == 6
    stream.result_at(1)
    assert stream.next_index == 2 and stream.filter.stats.frames == 2


def test_fixed_lag_read_keeps_what_left_the_filter_keyframe(synthetic_sequence):
    """With the asked-for frames known, the look-ahead read of frame k is completed by what the
    filter keyframes left inside the window held of k's pixels; the final read is unchanged."""
    seq = synthetic_sequence

    def frame(i):
        return seq.frames[i].gray, seq.frames[i].pose

    asked = [0, 6, 12]
    plain = FilterStream(frame, seq.camera, lookahead=12, num_frames=len(seq))
    lagged = FilterStream(frame, seq.camera, lookahead=12, num_frames=len(seq), keyframes=asked)
    gained = 0
    for k in asked:
        a, b = plain.result_at(k), lagged.result_at(k)
        np.testing.assert_array_equal(b.depth[a.valid], a.depth[a.valid])
        assert np.all(b.valid[a.valid])
        filled = b.valid & ~a.valid
        gained += int(filled.sum())
        if filled.sum() > 50:
            assert np.median(_abs_rel(b.depth, seq.gt_depth_working(k), filled)) < 0.05
        assert np.array_equal(np.isfinite(b.score), b.valid)
    assert lagged.filter.stats.keyframes >= 3 and gained > 500, gained


def test_bad_parameters_and_inputs_raise(synthetic_sequence):
    seq = synthetic_sequence
    with pytest.raises(ValueError, match=r'filter\.pixel_sigma'):
        DepthFilter(seq.camera, FilterConfig(pixel_sigma=0.0))
    with pytest.raises(ValueError, match=r'filter\.keyframe_parallax'):
        FilterConfig(keyframe_parallax=0.001).validate()
    for bad in ({'min_gradient': -1.0}, {'pose_sigma': -0.1}, {'fill_radius': -1}, {'seed_parallax': -1.0}):
        with pytest.raises(ValueError, match=rf'filter\.{next(iter(bad))}'):
            FilterConfig(**bad).validate()
    f = DepthFilter(seq.camera)
    with pytest.raises(ValueError, match='frame image'):
        f.process(np.zeros((10, 10), np.float32), seq.frames[0].pose)
    with pytest.raises(ValueError, match='frame pose'):
        f.process(seq.frames[0].gray, np.full((4, 4), np.nan))


def test_dense_neighbour_range_matches_the_window_gather(synthetic_sequence):
    """The seed bracket's two paths (window gather for a few rows, min / max filters over the
    image for many) give the same ranges, to the bit."""
    seq = synthetic_sequence
    f = DepthFilter(seq.camera)
    for frame in seq.frames[:8]:
        f.process(frame.gray, frame.pose)
    key = f.key
    rows = torch.arange(int(key.flat.numel()))
    lo_dense, hi_dense = f._neighbour_range_dense(key, rows)
    parts = [f._neighbour_range(key, rows[s : s + 500]) for s in range(0, int(rows.numel()), 500)]
    lo_gather, hi_gather = (torch.cat([p[i] for p in parts]) for i in (0, 1))
    assert torch.isfinite(lo_dense).any() and torch.isinf(lo_dense).any()
    assert torch.equal(lo_dense, lo_gather) and torch.equal(hi_dense, hi_gather)
