"""Online self-supervised adaptation (core + evaluation): prequential scoring, ground-truth
invariance, guarded rollback of a poisoned update, the replay buffer and the loss terms."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from depth_fusion_ros.adaptation.adapter import Adapter
from depth_fusion_ros.adaptation.config import AdaptConfig
from depth_fusion_ros.adaptation.fusion_trust import (
    FusionTrust,
    fusion_trust,
    points_scale,
    trust_from_json,
    untrusted_reason,
)
from depth_fusion_ros.adaptation.keyframes import KeyframeAssembler
from depth_fusion_ros.adaptation.losses import photometric
from depth_fusion_ros.adaptation.online import OnlineAdaptation, WeightSlot
from depth_fusion_ros.adaptation.replay import ReplayBuffer
from depth_fusion_ros.adaptation.sample import Neighbour, make_sample
from depth_fusion_ros.data.sequence import Frame, Sequence
from depth_fusion_ros.evaluation.context import EvalOptions, KeyframeContext
from depth_fusion_ros.evaluation.methods.adapted import (
    adaptation_run,
    keyframe_sample,
    observe_keyframe,
    single_view_adapted,
)
from depth_fusion_ros.evaluation.methods.fusion import fuse_automatic

pytestmark = pytest.mark.usefixtures('one_torch_thread')

#: Small and quick: two steps per keyframe, one replayed keyframe.
FAST = {'steps_per_keyframe': 2, 'replay_per_step': 1, 'min_points': 5}


def _hold_updates(adapter: Adapter, timeout: float) -> tuple[threading.Event, threading.Event]:
    """Hold each ``adapter.observe`` at a gate (as a slow update would): returns the gate and
    an event set when an update reached it."""
    gate, entered = threading.Event(), threading.Event()
    observe = adapter.observe

    def held(sample, abort=None, behind=False):
        entered.set()
        gate.wait(timeout)
        return observe(sample, abort, behind)

    adapter.observe = held
    return gate, entered


def _options(model: str, **params) -> EvalOptions:
    return EvalOptions(frames=None, single_view=model, params={'adaptation': {**FAST, **params}})


def _gt_sample(seq: Sequence, i: int, scale: float = 1.0, photometric_views: bool = False):
    """A sample whose 'multi-view' points are the ground truth (times ``scale``), every 7th pixel."""
    gt = seq.gt_depth_working(i)
    depth = np.full(gt.shape, np.nan, np.float32)
    depth[::7, ::7] = gt[::7, ::7] * scale
    score = np.where(np.isfinite(depth), 1.0, np.nan).astype(np.float32)
    f = seq.frames[i]
    nb = [Neighbour(seq.frames[j].rgb, seq.frames[j].pose) for j in (i - 1, i + 1) if 0 <= j < len(seq)]
    return make_sample(
        i,
        f.rgb,
        seq.camera,
        depth,
        score,
        select_fraction=1.0,
        pose=f.pose if photometric_views else None,
        neighbours=nb if photometric_views else None,
    )


def test_prediction_of_keyframe_k_comes_from_weights_trained_on_keyframes_before_k_only(
    small_sequence, tiny_model
):
    seq, options = small_sequence, _options(tiny_model)
    shared: dict = {}
    scored = [single_view_adapted(KeyframeContext(seq, i, options, shared)).depth for i in range(4)]
    run = adaptation_run(KeyframeContext(seq, 0, options, shared))
    assert run.adapter.counters.updated >= 2  # it did learn

    replay_shared: dict = {}
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**FAST, 'seed': 0}))
    for k in range(4):
        expected = adapter.predictor().predict(seq.frames[k].rgb)
        np.testing.assert_array_equal(scored[k], expected)  # bit-identical
        ctx = KeyframeContext(seq, k, options, replay_shared)
        # the targets as the fusion of this prediction moved them (fusion_trust.points_scale)
        fused = fuse_automatic(ctx, expected, adapter.predictor().output_kind, source='adapted')
        trust = fusion_trust(fused.decision, fused.decision_reason, fused.withheld, fused.evidence)
        adapter.observe(keyframe_sample(ctx, adapter.config, trust))
    # Keyframe 0 is predicted by the untouched network, later ones by adapted weights.
    first = Adapter.from_spec(tiny_model).predictor().predict(seq.frames[3].rgb)
    assert not np.array_equal(scored[3], first)


def test_adapted_weights_do_not_depend_on_ground_truth(small_sequence, tiny_model):
    rng = np.random.default_rng(0)
    noisy = Sequence(
        small_sequence.name,
        small_sequence.camera,
        [
            Frame(f.index, f.stamp, f.rgb, f.pose, rng.uniform(0.1, 9.0, f.depth.shape).astype(np.float32))
            for f in small_sequence.frames
        ],
        small_sequence.gt_camera,
    )
    states = []
    for seq in (small_sequence, noisy):
        options, shared = _options(tiny_model), {}
        for i in range(3):
            ctx = KeyframeContext(seq, i, options, shared)
            observe_keyframe(ctx, adaptation_run(ctx))
        states.append(adaptation_run(KeyframeContext(seq, 0, options, shared)).adapter.net.state_dict())
    assert states[0].keys() == states[1].keys()
    for key in states[0]:
        assert torch.equal(states[0][key], states[1][key]), key
    untouched = Adapter.from_spec(tiny_model).net.state_dict()
    assert any(not torch.equal(states[0][k], untouched[k]) for k in states[0])


def test_guard_rolls_back_a_poisoned_update_and_restores_weights_and_optimiser(small_sequence, tiny_model):
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**FAST, 'steps_per_keyframe': 4}))
    for i in range(4):
        assert adapter.observe(_gt_sample(small_sequence, i)).status == 'updated'
    weights = {k: v.clone() for k, v in adapter.net.state_dict().items()}
    optimiser_steps = adapter.optimizer.state_dict()['state'][0]['step'].clone()
    # Every multi-view depth of this keyframe (held-out points included) is 4x wrong, in the
    # direction away from the truth for the network as it is now (which has not converged).
    current = adapter.predictor().predict(small_sequence.frames[4].rgb)
    ratio = np.nanmedian(current / small_sequence.gt_depth_working(4))
    # A long update without replay (the damage 4 default steps with replay do is within the
    # guard's tolerance: the guard judges harm, not intent).
    adapter.config.steps_per_keyframe, adapter.config.replay_per_step = 30, 0
    report = adapter.observe(_gt_sample(small_sequence, 4, scale=0.25 if ratio < 1 else 4.0))
    adapter.config.steps_per_keyframe, adapter.config.replay_per_step = 4, 1
    assert report.status == 'rolled_back'
    assert report.guard.after > report.guard.before
    assert adapter.counters.rolled_back == 1 and adapter.version == 4
    for key, value in adapter.net.state_dict().items():
        assert torch.equal(value, weights[key]), key
    assert torch.equal(adapter.optimizer.state_dict()['state'][0]['step'], optimiser_steps)
    assert all(s.key != 4 for s in adapter.buffer)  # a rejected keyframe is not replayed
    # A sound keyframe afterwards is accepted again.
    assert adapter.observe(_gt_sample(small_sequence, 5)).status == 'updated'


def test_a_restart_gives_back_the_loaded_weights_with_an_empty_replay_and_a_fresh_optimiser(
    small_sequence, tiny_model
):
    """The node restarts the adaptation when the poses every earlier keyframe's points came
    from were another frame's: nothing learnt from them may stay, in the weights, the replay
    or Adam's moments."""
    config = AdaptConfig.from_dict({**FAST, 'start_coverage': 0.5})
    adapter = Adapter.from_spec(tiny_model, config)
    loaded = {k: v.clone() for k, v in adapter.net.state_dict().items()}
    for i in range(3):
        assert adapter.observe(_gt_sample(small_sequence, i, scale=1.5)).status == 'updated'
    assert len(adapter.buffer) == 3 and adapter.coverage_needed() == config.min_coverage
    report = adapter.restart(7, 'the poses were of another frame')
    assert (report.status, report.key, report.version) == ('restarted', 7, 4)
    assert adapter.version == 4 and adapter.counters.restarts == 1 and adapter.accepted == 0
    for key, value in adapter.net.state_dict().items():
        assert torch.equal(value, loaded[key]), key
    assert len(adapter.buffer) == 0 and len(adapter.optimizer.state) == 0
    assert adapter.coverage_needed() == 0.5  # the start's coverage again: these are the loaded weights
    rgb = small_sequence.frames[4].rgb
    np.testing.assert_array_equal(
        adapter.predictor().predict(rgb), Adapter.from_spec(tiny_model).predictor().predict(rgb)
    )
    assert adapter.observe(_gt_sample(small_sequence, 3)).status == 'updated'  # and it learns again
    assert adapter.version == 5 and len(adapter.buffer) == 1


def test_the_training_thread_restarts_before_its_next_keyframe_and_lets_earlier_ones_go(
    small_sequence, tiny_model
):
    """A restart from key 3: inference gets the loaded weights back at once, the update in
    hand stops, the keyframes 1-2 still queued and keyframe 2 submitted after it are not
    trained on; keyframe 3 is."""
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict(FAST))
    assert adapter.observe(_gt_sample(small_sequence, 5, scale=1.5)).status == 'updated'
    slot = WeightSlot(Adapter.from_spec(tiny_model).predictor())  # the node's: the loaded weights
    rgb = small_sequence.frames[4].rgb
    loaded = Adapter.from_spec(tiny_model).predictor().predict(rgb)
    gate, entered = _hold_updates(adapter, 60.0)
    reports = []
    online = OnlineAdaptation(adapter, slot, queue_size=4, on_report=reports.append)
    slot.swap(adapter.predictor(), adapter.version)  # inference on the learnt weights
    assert not np.array_equal(slot.get()[0].predict(rgb), loaded)
    try:
        online.submit(_gt_sample(small_sequence, 0, scale=1.5))
        assert entered.wait(60.0)  # taken, and held at the gate
        for i in (1, 2):  # these two wait
            online.submit(_gt_sample(small_sequence, i, scale=1.5))
        assert online.restart(3, 'turned') == 2 and online.stale == 2
        np.testing.assert_array_equal(slot.get()[0].predict(rgb), loaded)  # at once
        assert online.submit(_gt_sample(small_sequence, 2, scale=1.5))  # no drop, just not trained on
        assert online.stale == 3
        gate.set()
        assert online.wait_idle(60.0)
        assert [(r.status, r.reason) for r in reports] == [('skipped', 'stopped'), ('restarted', 'turned')]
        assert not online.learnt and slot.version == adapter.version == 2
        np.testing.assert_array_equal(slot.get()[0].predict(rgb), loaded)
        online.submit(_gt_sample(small_sequence, 3))
        assert online.wait_idle(60.0)
    finally:
        assert online.stop()
    assert [r.key for r in reports] == [0, 3, 3] and reports[-1].status == 'updated' and online.learnt
    assert slot.version == 3


def test_a_step_that_raises_leaves_the_weights_and_optimiser_as_before(
    small_sequence, tiny_model, monkeypatch
):
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**FAST, 'steps_per_keyframe': 3}))
    assert adapter.observe(_gt_sample(small_sequence, 0)).status == 'updated'
    weights = {k: v.clone() for k, v in adapter.net.state_dict().items()}
    moments = adapter.optimizer.state_dict()['state'][0]['exp_avg'].clone()
    real_step, calls = adapter.optimizer.step, []

    def failing_step():  # two good steps, then one that fails half-way
        calls.append(1)
        real_step()
        if len(calls) == 3:
            raise RuntimeError('injected')

    monkeypatch.setattr(adapter.optimizer, 'step', failing_step)
    with pytest.raises(RuntimeError, match='injected'):
        adapter.observe(_gt_sample(small_sequence, 1))
    for key, value in adapter.net.state_dict().items():
        assert torch.equal(value, weights[key]), key
    assert torch.equal(adapter.optimizer.state_dict()['state'][0]['exp_avg'], moments)


def test_a_compile_session_in_another_thread_does_not_break_the_optimiser_step(small_sequence, tiny_model):
    """torch's compile flag is process-wide: a session starting or ending during Adam's grouped
    step gave it tensors and floats (TypeError in the composed graph). Sessions run inside
    COMPILE_LOCK (the compiled calls hold it), so the adaptation step never sees one change."""
    import time

    from depth_fusion_ros.compile_lock import COMPILE_LOCK

    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**FAST, 'steps_per_keyframe': 4}))
    stop = threading.Event()

    def compiler() -> None:  # what a compiled call does: flag up and down under the lock
        # Other threads run both while the flag is up and while the lock is free: a thread
        # that took the lock again at once (Python's lock is not fair) starved the step for a
        # minute, and one that only yielded with the flag down never changed it under a step.
        while not stop.is_set():
            with COMPILE_LOCK, torch.compiler._compile_session_context():
                time.sleep(0)
            time.sleep(0)

    thread = threading.Thread(target=compiler, daemon=True)
    thread.start()
    try:
        reports = [adapter.observe(_gt_sample(small_sequence, i)) for i in range(4)]
    finally:
        stop.set()
        thread.join()
    assert all(r.status == 'updated' for r in reports), [r.status for r in reports]


def test_too_few_points_is_skipped_and_counted(small_sequence, tiny_model):
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**FAST, 'min_points': 10_000}))
    report = adapter.observe(_gt_sample(small_sequence, 0))
    assert report.status == 'skipped' and 'too_few_points' in report.reason
    assert adapter.counters.skipped == 1 and adapter.version == 0


def test_points_on_one_corner_of_the_view_are_not_trained_on(small_sequence, tiny_model):
    """A live filter's first points lie on the nearest object; one update on them moved the whole
    network's scale to that object's error. Such a keyframe is skipped; a view-wide one is not."""
    sample = _gt_sample(small_sequence, 0)
    h, w = sample.rgb.shape[:2]
    corner = (sample.train_uv[:, 0] < w / 4) & (sample.train_uv[:, 1] < h / 3)
    sample.train_uv, sample.train_depth = sample.train_uv[corner], sample.train_depth[corner]
    assert corner.sum() >= 20 and sample.coverage() == 4 / 48  # 2 x 2 cells of the 8 x 6 grid
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict(FAST))
    report = adapter.observe(sample)
    assert report.status == 'skipped' and report.reason.startswith('too_little_coverage (8% of the image')
    assert adapter.counters.reasons == {'too_little_coverage': 1} and adapter.version == 0
    assert _gt_sample(small_sequence, 1).coverage() >= 0.9
    assert adapter.observe(_gt_sample(small_sequence, 1)).status != 'skipped'
    everywhere = Adapter.from_spec(
        tiny_model, AdaptConfig.from_dict({**FAST, 'min_coverage': 0.0, 'start_coverage': 0.0})
    )
    assert everywhere.observe(sample).status != 'skipped'  # 0: any coverage


def test_a_keyframe_whose_points_the_fusion_would_not_trust_is_not_trained_on(small_sequence, tiny_model):
    """When all but a small share of the points have a std that says they may be more than
    ``max_relative_std`` off (a focal length the check could not verify, under rotation: each
    biased alike), the fusion's guard trusts none of them; trained on, they made a hand-held
    stream's network 1.3x worse. Such a keyframe is skipped."""
    gt = small_sequence.gt_depth_working(0)
    depth = np.full(gt.shape, np.nan, np.float32)
    depth[::7, ::7] = gt[::7, ::7]
    score = np.where(np.isfinite(depth), 1.0, np.nan).astype(np.float32)
    frame = small_sequence.frames[0]

    def sample(relative_std, limit=0.15):
        std = (depth * relative_std).astype(np.float32)
        return make_sample(
            0,
            frame.rgb,
            small_sequence.camera,
            depth,
            score,
            select_fraction=1.0,
            mv_std=std,
            max_relative_std=limit,
        )

    assert np.isnan(_gt_sample(small_sequence, 0).precise_fraction)  # no std: nothing known, trained on
    half = np.where(np.arange(depth.shape[1]) < depth.shape[1] // 2, 0.05, 0.25)[None, :]
    halved = sample(half)
    assert 0.3 < halved.precise_fraction < 0.7
    assert len(halved.train_uv) == len(_gt_sample(small_sequence, 0).train_uv)  # every point still a target
    vague = sample(0.25)
    assert vague.precise_fraction == 0.0
    adapter = Adapter.from_spec(
        tiny_model, AdaptConfig.from_dict({**FAST, 'guard_z': 0.0, 'guard_tolerance': 1.0})
    )
    report = adapter.observe(vague)
    assert report.status == 'skipped' and report.reason.startswith('imprecise_points (0% of the points')
    assert adapter.counters.reasons == {'imprecise_points': 1} and adapter.version == 0
    assert adapter.observe(sample(0.25, limit=0.3)).status == 'updated'  # a looser limit trusts them


def test_a_keyframe_the_fusion_trusted_none_of_is_not_trained_on(small_sequence, tiny_model):
    """Points wrong together (7-Scenes with its poses given inverted) pass the adaptation's own
    tests, which judge them on points of the same kind; the fusion's guard, which sees how they
    fit the single view, trusted none of them (``single_view``), yet they made the single view
    1.9x worse. A keyframe with that verdict (or withheld) is skipped; ``follow_fusion_guard``
    false trains on it as before, and the other verdicts are trusted."""
    assert untrusted_reason('full', 'consistent multi-view points') == ''
    assert untrusted_reason('scale_only', 'x') == '' and untrusted_reason('single_scaled') == ''
    said = untrusted_reason('single_view', 'stage 2 kept 71 of 148 stage-1 points (< 0.5)')
    assert said == (
        'the fusion trusted none of its points (single_view: stage 2 kept 71 of 148 stage-1 points (< 0.5))'
    )
    assert untrusted_reason('full', 'no alignment', withheld=True).startswith('the fusion trusted none')
    sample = _gt_sample(small_sequence, 0)
    sample.untrusted = said
    config = {**FAST, 'guard_z': 0.0, 'guard_tolerance': 1.0}
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict(config))
    report = adapter.observe(sample)
    assert report.status == 'skipped' and report.reason == f'untrusted_points ({said})'
    assert adapter.counters.reasons == {'untrusted_points': 1} and adapter.version == 0
    sample.untrusted = ''
    assert adapter.observe(sample).status == 'updated'
    sample.untrusted = said
    ignoring = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**config, 'follow_fusion_guard': False}))
    assert ignoring.observe(sample).status == 'updated'


def test_a_fusion_verdict_is_read_by_its_exact_stamp():
    """``fused/decision`` says the keyframe's stamp in seconds, which a float holds to about
    240 ns at a 2026 stamp; the adaptation matches the verdict by ``stamp_ns``, exact. A
    message without it is an error naming it (counted as ``bad_decision`` by the node)."""
    stamp_ns = 1_796_498_280_888_172_923
    verdict = {'stamp': stamp_ns / 1e9, 'stamp_ns': stamp_ns, 'decision': 'single_view', 'reason': 'r'}
    text = json.dumps(verdict)
    assert round(json.loads(text)['stamp'] * 1e9) != stamp_ns  # why the seconds cannot key it
    said = 'the fusion trusted none of its points (single_view: r)'
    assert trust_from_json(text) == (stamp_ns, FusionTrust(said, 1.0))
    full = json.dumps({'stamp_ns': 5, 'decision': 'full', 'reason': 'ok', 'withheld': False})
    assert trust_from_json(full) == (5, FusionTrust('', 1.0))
    for bad in ('{"stamp": 1.5, "decision": "full"}', 'not json', '[]'):
        with pytest.raises(ValueError, match='unreadable fusion decision'):
            trust_from_json(bad)


def test_the_adaptation_trains_on_the_points_as_the_fusion_moved_them(small_sequence):
    """The fusion takes only the share ``scale_weight`` of the points' global scale when part
    of their std is shared (fusion/shared_scale.py); the verdict says so, and the adaptation's
    targets are the points moved by the same factor, so the network does not learn the bias
    the fusion kept out. A verdict that weighed nothing (or says nothing of it) moves nothing."""
    assert points_scale(None) == 1.0 and points_scale({'scale': 0.8}) == 1.0
    assert points_scale({'scale': 0.8, 'scale_weight': 1.0}) == 1.0
    assert points_scale({'scale': 0.8, 'scale_weight': 0.0}) == pytest.approx(1 / 0.8)
    assert points_scale({'scale': 0.8, 'scale_weight': 0.5}) == pytest.approx(0.8**-0.5)
    assert points_scale({'scale': None, 'scale_weight': 0.5}) == 1.0
    evidence = {'scale': 0.8, 'scale_weight': 0.25}
    verdict = {'stamp_ns': 7, 'decision': 'full', 'reason': 'ok', 'evidence': evidence}
    stamp_ns, trust = trust_from_json(json.dumps(verdict))
    factor = trust.points_scale
    assert (stamp_ns, trust.untrusted) == (7, '') and factor == pytest.approx(0.8**-0.75)

    seq = small_sequence
    depth = seq.gt_depth_working(0)
    score = np.where(np.isfinite(depth), 1.0, np.nan).astype(np.float32)
    rgb = seq.frames[0].rgb
    as_is = make_sample(0, rgb, seq.camera, depth, score, select_fraction=1.0)
    moved = make_sample(0, rgb, seq.camera, depth, score, select_fraction=1.0, points_scale=factor)
    np.testing.assert_allclose(moved.train_depth, as_is.train_depth * factor, rtol=1e-6)
    np.testing.assert_allclose(moved.holdout_depth, as_is.holdout_depth * factor, rtol=1e-6)
    # the graph's way: the verdict's part carries the factor to the assembled sample
    asm = KeyframeAssembler(select_fraction=1.0, neighbours=0)
    for part, value in (('trust', trust), ('rgb', rgb), ('depth', depth), ('score', score)):
        samples = asm.add(0, part, value, seq.camera if part == 'rgb' else None)
    assert len(samples) == 1 and samples[0].untrusted == ''
    np.testing.assert_allclose(samples[0].train_depth, moved.train_depth, rtol=1e-6)


def test_assembler_waits_for_the_fusion_verdict_once_verdicts_are_known(small_sequence):
    """Without a fusion_node no verdict ever comes and nothing waits; once one has come, a
    keyframe waits for its own (it comes after the fusion, later than the other parts)."""
    seq = small_sequence
    asm = KeyframeAssembler(select_fraction=1.0, neighbours=0)
    depth = seq.gt_depth_working(0)
    parts = [('rgb', seq.frames[0].rgb), ('depth', depth), ('score', np.ones_like(depth))]

    def add(stamp):
        camera = {'rgb': seq.camera}
        return [s for part, v in parts for s in asm.add(stamp, part, v, camera.get(part))]

    out = add(10)
    assert len(out) == 1 and out[0].untrusted == ''
    assert asm.add(10, 'trust', FusionTrust()) == []  # a verdict for a keyframe already given: let go
    assert 10 not in asm._pending
    assert add(20) == []  # verdicts are known now: waits for its own
    out = asm.add(20, 'trust', FusionTrust('the fusion trusted none of its points (single_view)'))
    assert len(out) == 1 and out[0].untrusted.startswith('the fusion trusted none')
    assert asm.add(30, 'trust', FusionTrust()) == [] and len(add(30)) == 1  # a verdict first, then the parts


def test_the_first_update_needs_points_over_half_the_view(small_sequence, tiny_model):
    """The first updates set the network's scale for the whole view: until one is accepted a
    keyframe needs ``start_coverage`` (half the image), then ``min_coverage`` (a quarter)."""
    left = _gt_sample(small_sequence, 2)
    keep = left.train_uv[:, 0] < left.rgb.shape[1] * 3 / 8  # 3 of the grid's 8 columns
    left.train_uv, left.train_depth = left.train_uv[keep], left.train_depth[keep]
    assert 0.25 <= left.coverage() < 0.5
    adapter = Adapter.from_spec(
        tiny_model, AdaptConfig.from_dict({**FAST, 'guard_z': 0.0, 'guard_tolerance': 1.0})
    )
    assert adapter.coverage_needed() == 0.5
    first = adapter.observe(left)
    assert first.status == 'skipped' and first.reason.startswith('too_little_coverage')
    assert adapter.observe(_gt_sample(small_sequence, 0)).status == 'updated'
    assert adapter.coverage_needed() == 0.25
    assert adapter.observe(left).status == 'updated'


def test_photometric_term_is_lowest_at_the_true_scale(small_sequence, tiny_model):
    """Known poses make the photometric consistency metric: scaling the depth raises it."""
    seq = small_sequence
    sample = _gt_sample(seq, 2, photometric_views=True)
    adapter = Adapter.from_spec(tiny_model)
    prepared = adapter.prepare(sample)
    photo = prepared.photometric(60, 80)
    gt = torch.from_numpy(np.nan_to_num(seq.gt_depth_working(2), nan=5.0))[None, None]
    gt = torch.nn.functional.interpolate(gt, size=(60, 80), mode='area')
    errors = {
        s: float(photometric(torch.log(gt * s), photo.key, photo.neighbours, photo.k, photo.t_ok))
        for s in (0.5, 0.8, 1.0, 1.25, 2.0)
    }
    assert min(errors, key=errors.get) == 1.0, errors


def test_replay_buffer_is_bounded_and_draws_distinct_items():
    buf: ReplayBuffer[int] = ReplayBuffer(3)
    for i in range(5):
        buf.add(i)
    assert list(buf) == [2, 3, 4] and buf.recent(2) == [4, 3]
    draw = buf.draw(5, np.random.default_rng(0))
    assert sorted(draw) == [2, 3, 4]
    with pytest.raises(ValueError, match='capacity'):
        ReplayBuffer(0)


def test_assembler_waits_for_the_pose_once_poses_are_known(small_sequence):
    seq = small_sequence
    asm = KeyframeAssembler(select_fraction=1.0, neighbours=1, min_baseline=0.0)
    depth = seq.gt_depth_working(0)
    score = np.ones_like(depth)
    # No pose topic: complete with image + depth + score (sparse term only).
    out = (
        asm.add(10, 'rgb', seq.frames[0].rgb, seq.camera)
        + asm.add(10, 'depth', depth)
        + asm.add(10, 'score', score)
    )
    assert len(out) == 1 and out[0].pose is None
    # Once a pose has been seen, a keyframe waits for its own; the previous posed one is its neighbour.
    assert asm.add(20, 'pose', seq.frames[1].pose) == []
    out = (
        asm.add(20, 'rgb', seq.frames[1].rgb, seq.camera)
        + asm.add(20, 'depth', depth)
        + asm.add(20, 'score', score)
    )
    assert len(out) == 1 and out[0].pose is not None and out[0].neighbours == []
    out = (
        asm.add(30, 'rgb', seq.frames[2].rgb, seq.camera)
        + asm.add(30, 'depth', depth)
        + asm.add(30, 'score', score)
    )
    assert out == []
    out = asm.add(30, 'pose', seq.frames[2].pose)
    assert len(out) == 1 and out[0].has_photometric and len(out[0].neighbours) == 1


def test_assembler_waits_for_the_std_once_stds_are_known(small_sequence):
    seq = small_sequence
    asm = KeyframeAssembler(select_fraction=1.0, neighbours=0, max_relative_std=0.1)
    depth = seq.gt_depth_working(0)
    score = np.ones_like(depth)
    parts = [('rgb', seq.frames[0].rgb), ('depth', depth), ('score', score)]
    out = [
        s for part, value in parts for s in asm.add(10, part, value, seq.camera if part == 'rgb' else None)
    ]
    assert len(out) == 1 and np.isnan(out[0].precise_fraction)  # no std topic: complete without
    assert asm.add(20, 'std', depth * 0.2) == []
    out = [
        s for part, value in parts for s in asm.add(20, part, value, seq.camera if part == 'rgb' else None)
    ]
    assert len(out) == 1 and out[0].precise_fraction == 0.0  # 0.2 > 0.1 everywhere
    out = [
        s for part, value in parts for s in asm.add(30, part, value, seq.camera if part == 'rgb' else None)
    ]
    assert out == []  # waits for its std now
    out = asm.add(30, 'std', depth * 0.05)
    assert len(out) == 1 and out[0].precise_fraction == 1.0


def test_a_mount_turn_re_poses_the_neighbours_and_the_waiting_poses(small_sequence):
    """A keyframe's photometric neighbours posed before multi_view_node turned the camera and
    the keyframe after it would pair two cameras; ``repose`` turns the kept ones too, so the
    relative pose of the pair is that of one camera."""
    seq = small_sequence
    asm = KeyframeAssembler(select_fraction=1.0, neighbours=1, min_baseline=0.0)
    depth = seq.gt_depth_working(0)
    score = np.ones_like(depth)
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('x', 2.0, degrees=True).as_matrix()
    for i, stamp in enumerate((10, 20)):  # posed without the turn
        asm.add(stamp, 'pose', seq.frames[i].pose @ np.linalg.inv(turn))
        asm.add(stamp, 'rgb', seq.frames[i].rgb, seq.camera)
    asm.add(10, 'depth', depth)
    assert len(asm.add(10, 'score', score)) == 1  # complete: a neighbour; 20 waits
    assert asm.repose(turn) == 2  # the neighbour and the waiting pose
    asm.add(20, 'depth', depth)
    out = asm.add(20, 'score', score)
    assert asm.add(30, 'pose', seq.frames[2].pose) == []  # posed with the turn
    out += asm.add(30, 'rgb', seq.frames[2].rgb, seq.camera) + asm.add(30, 'depth', depth)
    out += asm.add(30, 'score', score)
    assert [s.key for s in out] == [20, 30]
    np.testing.assert_allclose(out[0].pose, seq.frames[1].pose, atol=1e-12)
    np.testing.assert_allclose(out[0].neighbours[0].pose, seq.frames[0].pose, atol=1e-12)
    np.testing.assert_allclose(out[1].neighbours[0].pose, seq.frames[1].pose, atol=1e-12)


def test_bad_settings_are_clear_errors():
    with pytest.raises(ValueError, match=r'adaptation\.lr'):
        AdaptConfig.from_dict({'lr': 0.0})
    with pytest.raises(ValueError, match=r'adaptation\.min_precise_fraction'):
        AdaptConfig.from_dict({'min_precise_fraction': 1.5})
    with pytest.raises(ValueError, match=r'adaptation\.max_relative_std'):
        AdaptConfig.from_dict({'max_relative_std': 0.0})
    with pytest.raises(ValueError, match='unknown adaptation parameter'):
        AdaptConfig.from_dict({'learning_rate': 1e-3})
    with pytest.raises(ValueError, match='simulated'):
        Adapter.from_spec('simulated')


def test_an_update_made_while_behind_takes_the_shorter_steps(small_sequence, tiny_model):
    """Keyframes faster than updates (a live node on a small CPU): the training thread sees
    another keyframe waiting or one dropped, and that update takes ``steps_when_behind`` steps
    (the same replay); one keyframe at a time keeps the full update."""
    config = AdaptConfig.from_dict({**FAST, 'steps_per_keyframe': 3, 'steps_when_behind': 1})
    with pytest.raises(ValueError, match=r'adaptation\.steps_when_behind'):
        AdaptConfig.from_dict({'steps_when_behind': 0})
    adapter = Adapter.from_spec(tiny_model, config)
    draws: list[int] = []
    draw = adapter.buffer.draw
    adapter.buffer.draw = lambda n, rng: draws.append(n) or draw(n, rng)
    assert adapter.observe(_gt_sample(small_sequence, 0)).steps == 3
    report = adapter.observe(_gt_sample(small_sequence, 1), behind=True)
    assert report.status == 'updated' and report.behind and report.steps == 1
    assert draws == [1, 1, 1, 1]  # FAST's replay_per_step, behind or not

    reports = []
    gate, entered = _hold_updates(adapter, 30.0)
    slot = WeightSlot(adapter.predictor())
    now = [0.0]  # the keyframes' arrival times, as the test says them
    online = OnlineAdaptation(adapter, slot, queue_size=2, on_report=reports.append, clock=lambda: now[0])
    try:
        online.submit(_gt_sample(small_sequence, 2))  # taken at once, held at the gate
        assert entered.wait(30)
        for i in (3, 4, 5):  # 3 is dropped for 5: the queue holds two
            online.submit(_gt_sample(small_sequence, i))
        gate.set()
        assert online.wait_idle(60)
        assert online.dropped == 1
        # 2: the first update (how fast updates and keyframes come is not known yet: short);
        # 4: 5 waited behind it (and 3 had been dropped); 5: nothing waiting or dropped since,
        # but the last update took longer than the keyframes came (all at once here)
        assert [(r.key, r.behind) for r in reports] == [(2, True), (4, True), (5, True)]
        assert adapter.counters.behind == 4 and reports[1].steps == 1  # keyframes 1, 2, 4, 5
        now[0] = 1000.0  # the next keyframe comes long after the last update ended: caught up
        online.submit(_gt_sample(small_sequence, 0))
        assert online.wait_idle(60)
        assert reports[-1].key == 0 and not reports[-1].behind and reports[-1].steps == 3
        now[0] = 1000.001  # and one that comes faster than that update took: behind again
        online.submit(_gt_sample(small_sequence, 1))
        assert online.wait_idle(60)
        assert reports[-1].key == 1 and reports[-1].behind and reports[-1].steps == 1
    finally:
        online.stop()


def test_keyframes_skipped_while_behind_are_not_counted_as_trained(small_sequence, tiny_model):
    """``counters.behind`` counts updates that trained (kept or rolled back), not keyframes the
    adapter skipped without a step (too few points) while training was behind."""
    adapter = Adapter.from_spec(tiny_model, AdaptConfig.from_dict({**FAST, 'min_points': 10_000}))
    report = adapter.observe(_gt_sample(small_sequence, 0), behind=True)
    assert report.status == 'skipped' and adapter.counters.skipped == 1
    assert adapter.counters.behind == 0


def test_a_time_offset_correction_re_reads_the_neighbours_and_the_waiting_poses(small_sequence):
    """Keyframes posed at a wrong time offset, then read again at the corrected one by
    multi_view_node: the neighbour kept and the pose waiting take the new poses (the
    keyframes the assembler has not heard of are left to the caller), so the pairs of the
    keyframes to come compare poses read at one offset."""
    seq = small_sequence
    asm = KeyframeAssembler(select_fraction=1.0, neighbours=1, min_baseline=0.0)
    depth = seq.gt_depth_working(0)
    score = np.ones_like(depth)
    late = np.eye(4)
    late[:3, 3] = (0.03, 0.0, 0.0)  # where the camera was 30 ms later
    for i, stamp in enumerate((10, 20)):
        asm.add(stamp, 'pose', seq.frames[i].pose @ late)
        asm.add(stamp, 'rgb', seq.frames[i].rgb, seq.camera)
    asm.add(10, 'depth', depth)
    assert len(asm.add(10, 'score', score)) == 1  # complete: a neighbour; 20 waits
    truth = {10: seq.frames[0].pose, 20: seq.frames[1].pose, 25: seq.frames[1].pose}
    assert asm.reread(truth) == {10, 20}  # 25: not heard of
    asm.add(20, 'depth', depth)
    out = asm.add(20, 'score', score)
    out += asm.add(30, 'pose', seq.frames[2].pose) + asm.add(30, 'rgb', seq.frames[2].rgb, seq.camera)
    out += asm.add(30, 'depth', depth) + asm.add(30, 'score', score)
    assert [s.key for s in out] == [20, 30]
    np.testing.assert_allclose(out[0].pose, seq.frames[1].pose, atol=1e-12)
    np.testing.assert_allclose(out[0].neighbours[0].pose, seq.frames[0].pose, atol=1e-12)
    np.testing.assert_allclose(out[1].neighbours[0].pose, seq.frames[1].pose, atol=1e-12)


def test_the_cudnn_switch_gives_the_flag_back_even_after_a_failed_step():
    """Training on a GPU turns cuDNN off (adapter.py ``_convolutions``); a step that raises must
    not leave it off for the process's inference."""
    from depth_fusion_ros.adaptation.adapter import _cudnn_disabled

    was = torch.backends.cudnn.enabled
    with pytest.raises(RuntimeError, match='a failed step'), _cudnn_disabled():
        assert not torch.backends.cudnn.enabled
        raise RuntimeError('a failed step')
    assert torch.backends.cudnn.enabled == was


def test_the_anchor_lets_the_scale_follow_and_holds_the_shape(small_sequence, tiny_model):
    """The anchor term (``adaptation.anchor_weight``) is zero at the starting network's depth
    and for any change of its scale, and grows with a change of its shape."""
    adapter = Adapter.from_spec(tiny_model, AdaptConfig(anchor_weight=1.0))
    prepared = adapter.prepare(_gt_sample(small_sequence, 2))
    with torch.no_grad():
        start = adapter._eval_forward(prepared.x)
        assert float(adapter._anchor_term(start, [prepared])) == pytest.approx(0.0, abs=1e-6)
        assert float(adapter._anchor_term(start + 0.3, [prepared])) == pytest.approx(0.0, abs=1e-6)
        shape = start.clone()
        shape[..., : shape.shape[-2] // 4, :] += 0.4  # a quarter of the rows moved: not a scale
        assert float(adapter._anchor_term(shape, [prepared])) == pytest.approx(0.1, rel=0.05)
