"""The synthetic stress cases end to end: fused is never worse than its single-view input.

Each case (data/synthetic/stress.py) is rendered small (160x120, a handful of frames) and
evaluated like ``depth-fusion evaluate --single-view simulated`` on one or two keyframes:
semi-dense multi-view depth, the simulated CNN prior, the fusion with its guard. Every case
runs with both multi-view methods: the filter (the default) and the paper's sweep (pinned).
"""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import (
    STRESS_CASES,
    SynthConfig,
    build_world,
    render_sequence,
    stress_config,
)
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.distance_bands import band_table
from depth_fusion_ros.evaluation.guard_report import decision_table
from depth_fusion_ros.evaluation.harness import evaluate_sequence, results_document
from depth_fusion_ros.fusion.guard import DECISIONS
from depth_fusion_ros.fusion.pipeline import FusionConfig
from depth_fusion_ros.geometry import relative_pose, rotation_angle
from depth_fusion_ros.multiview.filter_config import FilterConfig

W, H, FRAMES = 160, 120, 7
METHODS = ['single_view_simulated', 'fused', 'fused_unguarded']


def _steps(poses: np.ndarray) -> tuple[float, float]:
    moves = [relative_pose(poses[i], poses[i + 1]) for i in range(len(poses) - 1)]
    return (
        float(np.median([np.linalg.norm(T[:3, 3]) for T in moves])),
        float(np.degrees(np.median([rotation_angle(T[:3, :3]) for T in moves]))),
    )


#: Every case with seed 0, plus rotation seeds where the filter's few precise estimates were
#: biased together: seed 5 (consistent, 20 % too near everywhere: the global scale they gave
#: made it 1.34x the single-view MAE), seeds 2 and 29 (9-10 % of the measured estimates passed
#: the precision test, half of them the front surface's depth carried across its outline: 1.09x
#: and 1.23x with ``filter.min_published_fraction`` 0.05); each with the filter (the default
#: multi-view method) and the sweep.
CASES = [
    (name, seed, method)
    for name, seed in [(name, 0) for name in sorted(STRESS_CASES)]
    + [('rotation', 5), ('rotation', 2), ('rotation', 29)]
    for method in ('filter', 'sweep')
]


#: Per-case overrides for the short sequences: the lateral sweep spans its whole length in any
#: number of frames, so the 3 m of ``motion_blur`` and ``rolling_shutter`` would be 50 cm per
#: frame here; their sweep is cut to keep the stress cases' 3 cm per frame, and with it the
#: blur and the skew of that motion.
SHORT_OVERRIDES: dict[str, dict[str, float]] = {
    name: {'sweep': 0.03 * (FRAMES - 1)} for name in ('motion_blur', 'rolling_shutter')
}


@pytest.fixture(scope='module', params=CASES, ids=[f'{n}-{s}-{m}' for n, s, m in CASES])
def evaluated(request):
    name, seed, method = request.param
    cfg = stress_config(name, width=W, height=H, frames=FRAMES, seed=seed, **SHORT_OVERRIDES.get(name, {}))
    sequence = render_sequence(cfg)
    options = EvalOptions(
        frames=FRAMES,
        keyframes=[FRAMES // 2],
        single_view='simulated',
        width=W,
        height=H,
        params={'fusion': {'compile_kernel': False, 'mode': 'fast'}, 'multi_view': {'method': method}},
    )
    result = evaluate_sequence(sequence, METHODS, options, show_progress=False)
    return name, cfg, sequence, result, f'{name}-{seed}-{method}'


def test_stress_motions_have_the_reported_steps():
    _, rotation = build_world(stress_config('rotation', width=32, height=24, frames=5))
    step, deg = _steps(rotation.poses)
    assert step == pytest.approx(0.012, rel=0.1) and deg == pytest.approx(0.6, rel=0.05)
    cfg = stress_config('keyframes', width=32, height=24, frames=5)
    step, deg = _steps(build_world(cfg)[1].poses)
    assert step == pytest.approx(0.15, rel=0.02) and deg == pytest.approx(6.7, rel=0.02)
    assert cfg.stamp(1) - cfg.stamp(0) == pytest.approx(1 / 1.5, abs=1e-5)
    _, forward = build_world(stress_config('forward', width=32, height=24, frames=5))
    step, deg = _steps(forward.poses)
    assert step == pytest.approx(0.015, rel=1e-6) and deg < 0.2
    ahead = forward.poses[1][:3, 3] - forward.poses[0][:3, 3]
    # ahead, along the view (pitched down to the look-at target)
    assert np.dot(ahead / np.linalg.norm(ahead), forward.poses[0][:3, 2]) > 0.9
    blur = stress_config('motion_blur', width=32, height=24, frames=100)
    step, _ = _steps(build_world(blur)[1].poses)
    assert step == pytest.approx(0.03, rel=0.1) and blur.exposure_time * blur.fps == pytest.approx(1.0)
    rolling = stress_config('rolling_shutter', width=32, height=24, frames=100)
    assert _steps(build_world(rolling)[1].poses)[0] == pytest.approx(step) and rolling.readout_time == 0.03


def test_wrong_focal_tells_the_pipeline_wrong_intrinsics():
    sequence = render_sequence(stress_config('wrong_focal', width=32, height=24, frames=1))
    assert sequence.camera.fx == pytest.approx(1.1 * sequence.gt_camera.fx)
    assert sequence.camera.cx == sequence.gt_camera.cx


def test_pose_noise_jitters_the_told_poses_only():
    cfg = stress_config('pose_noise', width=32, height=24, frames=4)
    noisy = render_sequence(cfg)
    exact = render_sequence(stress_config('translation', width=32, height=24, frames=4))
    offsets = [relative_pose(a.pose, b.pose) for a, b in zip(noisy.frames, exact.frames, strict=True)]
    moved = [float(np.linalg.norm(T[:3, 3])) for T in offsets]
    turned = [float(np.degrees(rotation_angle(T[:3, :3]))) for T in offsets]
    assert all(0 < m < 0.02 for m in moved) and all(0 < t < 1.0 for t in turned)
    for a, b in zip(noisy.frames, exact.frames, strict=True):  # rendered at the true poses
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
    assert np.array_equal(render_sequence(cfg).frames[2].pose, noisy.frames[2].pose)  # seeded


#: Cases the guard does not catch yet (docs/fusion.md), by case id, bounded so that they
#: cannot get worse. None: with the sweep since the corrections fade with the distance to
#: their points (``guard.reach``); with the filter (the default since 2026-11-25) since the
#: guard weighs stage 2's support (``guard.min_inlier_ratio``): on rotation seed 5 the filter
#: published 151 estimates 59 % off, stage 2 kept 45 (0.30), and fusing them made the depth
#: 0.6 % worse than the single-view input.
KNOWN_MISSES: dict[str, float] = {}


def test_fused_is_never_worse_than_single_view(evaluated):
    _, _, _, result, case = evaluated
    single = result.records['single_view_simulated'].all.summary()['mae']
    fused = result.records['fused'].all.summary()['mae']
    if case in KNOWN_MISSES:
        assert fused <= KNOWN_MISSES[case] * single, (case, fused, single)
        if fused > single:
            pytest.xfail(f'{case}: fused MAE {fused:.3f} > single-view {single:.3f} (known miss)')
    assert fused <= single, (case, fused, single)


def test_decisions_are_recorded_and_reported(evaluated):
    name, _, sequence, result, _ = evaluated
    levels = result.records['fused'].extras['decision']
    assert len(levels) == 1 and 0 <= levels[0] < len(DECISIONS)
    if name == 'translation':  # the good case keeps per-point fusion
        assert DECISIONS[int(levels[0])] in ('full', 'fewer_points')
    doc = results_document([result], METHODS, EvalOptions())
    table = decision_table(doc)
    assert table is not None and sequence.name in table
    bands = band_table(doc)  # the fused errors by distance to Ω, recorded with the decision
    assert bands is not None and sequence.name in bands


def _causal_ratio(sequence, keyframe: int, fusion: dict, **stages: dict) -> float:
    """Fused / single-view MAE of one keyframe read causally, as the node reads the stream
    (online filter), with the node's fast fusion of at most 4096 points plus ``fusion`` and
    any other ``stage={...}`` parameters."""
    options = EvalOptions(
        frames=len(sequence),
        keyframes=[keyframe],
        single_view='simulated',
        width=320,
        height=240,
        neighbour_mode='online',
        params={'fusion': {'compile_kernel': False, 'mode': 'fast', 'max_points': 4096, **fusion}, **stages},
    )
    result = evaluate_sequence(sequence, ['single_view_simulated', 'fused'], options, show_progress=False)
    return (
        result.records['fused'].all.summary()['mae']
        / result.records['single_view_simulated'].all.summary()['mae']
    )


def test_a_causal_streams_first_keyframe_is_never_worse():
    """The node's view (causal filter, no look-ahead): rotation-heavy motion at 320x240, the
    first keyframe of the stream (frame 5). Every estimate there was born in the filter's
    first keyframe and measured by the same few frames; with two measurements enough
    (``first_keyframe_min_updates`` 2) they were biased together and the fusion made the depth
    1.33x worse than its single-view input; with the default it is not. (The certainty floor
    alone brings the biased case down to 1.02x, with its gain to 0.93x, the halo test alone to
    1.15x, and the points' scale weighed by their shared focal bias alone to 1.17x; all four
    are off here, to test the filter, and so is the edge cut.)"""
    sequence = render_sequence(stress_config('rotation', width=320, height=240, frames=8, seed=2))

    def ratio(first_keyframe_min_updates: int) -> float:
        fusion = {'stage1': 'all', 'certainty_floor': 0.0, 'certainty_gain': 0.0}
        fusion |= {'halo_min_step': 0.0, 'edge_ratio': 0.0}
        return _causal_ratio(
            sequence,
            5,
            fusion,
            filter={'first_keyframe_min_updates': first_keyframe_min_updates},
            guard={'shared_scale': False},
        )

    assert ratio(2) > 1.2
    assert ratio(FilterConfig().first_keyframe_min_updates) <= 1.0


def test_a_realistic_low_texture_streams_late_keyframe_is_never_worse():
    """A realistic-length causal stream (docs/fusion.md "Certainty floor"): low texture at
    320x240, the keyframe at frame 70, the node's fast fusion of at most 4096 points. The
    points sit on the few textured patches; the paper's normalised weights carried their
    corrections across the empty walls, where the single-view error is another one, and
    made the keyframe 1.15x worse than its input (the guard judged it ``full``: no evidence
    it reads tells this keyframe from those the long reach helps). With the certainty floor
    (default) the correction fades where the points' total weight is small, and it is not
    worse. The halo test and the edge cut (``edge_points.py``) are off in both, to test the
    floor: the halo test alone brings the keyframe to 0.89x (the halo's points were among those
    that carried the corrections), the edge cut alone to 0.89x."""
    sequence = render_sequence(stress_config('low_texture', width=320, height=240, frames=71, seed=0))
    off = {'halo_min_step': 0.0, 'edge_ratio': 0.0}
    assert _causal_ratio(sequence, 70, {'certainty_floor': 0.0, 'certainty_gain': 0.0, **off}) > 1.1
    assert _causal_ratio(sequence, 70, {'certainty_floor': FusionConfig().certainty_floor, **off}) <= 1.0


#: The simulated prior a quarter as wrong as the paper's (5 % per segment, 2.5 % global): the
#: error of a network adapted to the scene or of a good metric model, about 2-3x the points'.
PRECISE_PRIOR = {
    'segment_scale_sigma': 0.05,
    'segment_offset_sigma': 0.02,
    'global_scale_sigma': 0.025,
    'deformation_sigma': 0.015,
}


def test_a_precise_single_views_keyframe_is_not_made_worse():
    """A single-view depth almost as precise as the points (docs/fusion.md "A floor that
    follows the single-view depth's precision"): the default room, seed 0, keyframe 30 read
    causally. The points are right (1 % median error) but their residual against a 4 %
    network is mostly their own noise and the network's segment errors, which the normalised
    weights carried onto the back wall, where no point is: 1.10x worse than the input with the
    fixed floor alone (1.19-1.20x while the pose refinement tracked every frame from the told
    pose; from the previous frame's tracks its points moved a little). With the floor following
    the precision ratio (default) it is better than its input (0.83x). The halo test is off in
    both, to test the floor (it alone: 0.79x), and so is the edge cut."""
    sequence = render_sequence(SynthConfig(width=320, height=240, frames=31, seed=0))
    off = {'halo_min_step': 0.0, 'edge_ratio': 0.0}
    assert _causal_ratio(sequence, 30, {'certainty_gain': 0.0, **off}, simulated=PRECISE_PRIOR) > 1.05
    default = FusionConfig().certainty_gain
    assert _causal_ratio(sequence, 30, {'certainty_gain': default, **off}, simulated=PRECISE_PRIOR) <= 0.95
