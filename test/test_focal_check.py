"""The focal length check: a wrong camera_info focal length is found from the images and the
told poses (issue 11's wrong-focal stress case), a right one is not flagged, noisy poses do
not fake a disagreement, and ``evaluate`` corrects the camera when asked."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.harness import evaluate_sequence
from depth_fusion_ros.multiview.focal_check import (
    FocalCheck,
    FocalCheckConfig,
    FocalEstimate,
    censored,
    check_frames,
)

#: 320x240 over a 1 m sweep in 40 frames: a pair every two frames.
SIZE = {'width': 320, 'height': 240, 'frames': 40, 'seed': 5}
PAIRS = 12
#: A SLAM's keyframe poses: jittered by 5 mm and 0.3 deg, camera_info 5 % long, gain noise.
SLAM_NOISE = {'focal_error': 0.05, 'pose_noise_m': 0.005, 'pose_noise_deg': 0.3, 'gain_sigma': 0.1}


@pytest.fixture(scope='module')
def wrong_focal():
    return render_sequence(stress_config('wrong_focal', **SIZE))


def _check(sequence, **config) -> tuple[FocalEstimate | None, FocalCheck]:
    check = check_frames(sequence.camera, sequence.frames, FocalCheckConfig(pairs=PAIRS, **config))
    return check.result, check


def test_a_focal_length_ten_percent_long_is_found(wrong_focal):
    estimate, check = _check(wrong_focal)
    assert estimate is not None and check.done and estimate.pairs == PAIRS
    assert estimate.verdict == 'disagrees', estimate.message()
    assert estimate.scale == pytest.approx(1 / 1.1, abs=0.03) and estimate.stderr < 0.025
    corrected = estimate.corrected(wrong_focal.camera)
    assert corrected.fx == pytest.approx(wrong_focal.gt_camera.fx, rel=0.03)
    assert (corrected.cx, corrected.cy, corrected.size) == (
        wrong_focal.camera.cx,
        wrong_focal.camera.cy,
        wrong_focal.camera.size,
    )
    message = estimate.message()
    assert 'camera_info says fx 288.8 px' in message and 'check the calibration' in message
    assert 'lens distortion camera_info does not hold' in message
    assert not estimate.lens_distorted  # a focal error is not taken for a lens
    assert check.add(wrong_focal.frames[0].gray, wrong_focal.frames[0].pose) is None  # once


def test_the_right_focal_length_is_not_flagged():
    estimate, _ = _check(render_sequence(stress_config('translation', **SIZE)))
    assert estimate is not None and estimate.verdict == 'consistent', estimate.message()
    assert abs(estimate.scale - 1) < 0.04 and 'agrees' in estimate.message()
    assert not estimate.lens_distorted and 'k1' not in estimate.message()


def test_an_early_look_that_agrees_is_kept_and_the_check_goes_on(wrong_focal):
    """At ``lens_early_pairs`` the check fits its pairs once already: an estimate that agrees is
    kept as ``early`` (what bounds the filter's focal uncertainty until the result) and the
    check still reads all its pairs; one on a focal length 10 % long is not kept."""
    estimate, check = _check(render_sequence(stress_config('translation', **SIZE)))
    assert check.early is not None and check.early.pairs == 8, check.early
    assert check.early.verdict == 'consistent' and estimate.pairs == PAIRS
    _, check = _check(wrong_focal)
    assert check.early is None and check.result.verdict == 'disagrees'
    _, check = _check(wrong_focal, lens_early_pairs=0)  # no early look at all
    assert check.early is None


def test_a_lens_camera_info_does_not_hold_is_named():
    """The stress case ``lens_distortion`` (a barrel lens of k1 -0.1, camera_info without it,
    the rotation sweep): the pairs fit a radial distortion better than a focal change and
    agree on it, whatever the focal verdict; the warning says so and ``check-focal`` exits 6."""
    from depth_fusion_ros.cli.recordings import verdict_status

    lens = render_sequence(stress_config('lens_distortion', width=320, height=240, frames=100, seed=5))
    estimate, _ = _check(lens)
    assert estimate is not None and estimate.lens is not None, 'the check did not finish'
    assert estimate.lens_distorted, estimate.lens
    assert -0.12 < estimate.lens.k1 < -0.06 and estimate.lens.cost_ratio < 0.8
    assert 'the images fit a lens distortion k1 -0.' in estimate.message()
    assert verdict_status('check-focal', 'seq', estimate, 12, FocalCheckConfig(), 100) == 6
    pinhole, _ = _check(render_sequence(stress_config('rotation', width=320, height=240, frames=100, seed=5)))
    assert pinhole is not None and not pinhole.lens_distorted, pinhole.lens


def test_a_lens_is_reported_only_when_it_explains_the_pairs_clearly_better():
    from depth_fusion_ros.multiview.lens_fit import LensFit

    assert LensFit(-0.09, 0.003, 0.51, 0, 12).distorted
    assert not LensFit(-0.02, 0.003, 0.51, 0, 12).distorted  # too small to name
    assert not LensFit(0.15, 0.058, 0.98, 1, 12).distorted  # a focal change fits about as well
    assert not LensFit(0.3, 0.002, 0.80, 9, 12).distorted  # most pairs ran off the range
    assert not LensFit(0.0, float('inf'), float('inf'), 0, 0).distorted


def test_forward_motion_with_the_right_focal_length_is_not_corrected():
    """The forward stress stream of seed 29 (100 frames, exact focal length): with the detector's
    own keypoint positions the check said -7.2 % +- 1.0 % and corrected a right camera; with the
    matches tracked to sub-pixel (multiview/match_refinement.py) it agrees."""
    forward = render_sequence(stress_config('forward', width=320, height=240, frames=100, seed=29))
    estimate, _ = _check(forward)
    assert estimate is not None and estimate.verdict == 'consistent', estimate.message()


def test_a_fit_off_by_more_than_the_threshold_but_not_surely_is_suspect_not_agreement():
    """-6.7 % +- 1.4 % (a camera_info 10 % long read through the graph, seed 23) is not
    "agrees": it is said as suspect, with both focal lengths, and nothing is corrected; the
    recording check exits 5 for it."""
    from depth_fusion_ros.camera import PinholeCamera
    from depth_fusion_ros.cli.recordings import verdict_status

    check = FocalCheck(PinholeCamera(320, 240, 288.8, 288.8, 159.5, 119.5), FocalCheckConfig())
    verdicts = {s: check._verdict(s, e).verdict for s, e in ((0.933, 0.014), (1.03, 0.008), (0.90, 0.01))}
    assert verdicts == {0.933: 'suspect', 1.03: 'consistent', 0.90: 'disagrees'}
    suspect = check._verdict(0.933, 0.014)
    message = suspect.message()
    assert 'camera_info says fx 288.8 px' in message and 'fx 269.5 px best' in message
    assert 'kept' in message and 'check the calibration' in message and 'agrees' not in message
    assert verdict_status('check-focal', 'seq', suspect, 12, FocalCheckConfig(), 100) == 5


def test_a_focal_disagreement_a_lens_explains_as_well_is_suspect_and_not_taken():
    """A lens camera_info does not hold reads as a focal error under rotation; where a radial
    distortion fits the pairs about as well as the focal change (cost ratio under
    ``MIN_FOCAL_MARGIN``), the disagreement is ``suspect``: said with the lens, never corrected
    (``lens_distortion`` seed 231 read +6.9 % +- 0.7 % at a ratio of 1.03, and its correction
    fused the stream at 1.045x its input). A focal length 10 % long (ratios 1.27-1.73) is still
    corrected."""
    from depth_fusion_ros.multiview.lens_fit import MIN_FOCAL_MARGIN, LensFit

    check = FocalCheck(PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5), FocalCheckConfig())
    rival = check._verdict(1.069, 0.007, LensFit(-0.045, 0.02, 1.03, 0, 12))
    assert rival.verdict == 'suspect' and rival.lens_rivals and not rival.lens_distorted
    assert not rival.applied('correct')
    message = rival.message()
    assert 'fx 280.6 px best' in message
    assert 'a lens distortion k1 -0.045 fits the pairs about as well' in message
    assert 'fx 262.5 px kept' in message and 'distortion D' in message
    focal = check._verdict(0.922, 0.012, LensFit(-0.18, 0.06, 1.61, 6, 12))
    assert focal.verdict == 'disagrees' and focal.applied('correct') and not focal.lens_rivals
    assert check._verdict(0.922, 0.012, LensFit(-0.18, 0.06, MIN_FOCAL_MARGIN, 6, 12)).verdict == 'disagrees'
    assert not LensFit(-0.09, 0.003, 0.51, 0, 12).rivals_focal  # reported: taken instead
    assert not LensFit(-0.05, 0.003, 1.0, 0, 2).rivals_focal  # too few pairs to say
    # Only a disagreement is turned: an agreement a lens fits as well stays one.
    assert check._verdict(1.01, 0.01, LensFit(-0.05, 0.05, 1.0, 1, 12)).verdict == 'consistent'


def test_the_lens_of_the_stress_stream_that_read_as_a_focal_error_is_not_taken_for_one():
    """The rotation sweep through a barrel lens (k1 -0.1), seed 231, 100 frames at 320x240: its
    pairs fit a focal length 6.9 % long about as well as a lens, and the check keeps the told
    one."""
    seq = render_sequence(stress_config('lens_distortion', width=320, height=240, frames=100, seed=231))
    estimate = check_frames(seq.camera, seq.frames, FocalCheckConfig()).result
    assert estimate is not None and estimate.verdict == 'suspect', estimate.message()
    assert estimate.lens_rivals and not estimate.applied('correct')
    assert estimate.scale == pytest.approx(1.069, abs=0.02)


def test_noisy_poses_do_not_fake_a_disagreement():
    """4 mm and 0.25 deg of pose noise per frame: every match of a pair moves with its pose
    error, so the pairs disagree with each other, not with the focal length."""
    noisy = stress_config('pose_noise', **SIZE, pose_noise_m=0.004, pose_noise_deg=0.25)
    estimate, _ = _check(render_sequence(noisy))
    assert estimate is not None and estimate.verdict != 'disagrees', estimate.message()


def test_pairs_that_fit_at_the_end_of_the_range_leave_the_focal_length_unobservable():
    """A SLAM's keyframe stream (15 cm and 6.7 deg apart, poses jittered by 5 mm and 0.3 deg,
    camera_info 5 % long; seed 161): half the pairs fit best at half the focal length, as far as
    the fit reaches (a pose error is an angle, fewer pixels at a shorter focal length). Their
    median and its spread read -48 % +- 0.9 %, which the node took (fx 142 px for 262.5). Pairs
    at the range's end are censored: more than a tenth of them, and the focal length is
    unobservable, kept as told; one of twelve changes nothing."""
    slam = stress_config('keyframes', **SIZE | {'frames': 16, 'seed': 161}, **SLAM_NOISE)
    estimate, check = _check(render_sequence(slam))
    assert estimate is not None and estimate.verdict == 'unobservable', estimate.message()
    assert estimate.censored >= 2 and estimate.scale < 0.6  # the poses' noise, not a focal length
    assert estimate.poses_unfit
    assert not estimate.applied('correct') and check.early is None
    message = estimate.message()
    assert 'end of the range searched' in message and 'fx 275.6 px kept' in message
    assert 'camera_from_pose_frame' in message
    assert censored(np.array([0.5, 0.505, 0.51, 1.0, 1.96, 1.97, 1.99])).tolist() == [
        True,
        True,
        False,
        False,
        False,
        True,
        True,
    ]
    check = FocalCheck(PinholeCamera(320, 240, 288.8, 288.8, 159.5, 119.5), FocalCheckConfig())
    check.pairs = [SimpleNamespace(p1=np.zeros((40, 2)))] * PAIRS  # their count and matches are read
    assert check._verdict(0.9, 0.01, None, n_censored=1).verdict == 'disagrees'
    assert check._verdict(0.9, 0.01, None, n_censored=2).verdict == 'unobservable'


def test_a_camera_that_stands_still_gives_no_pairs(wrong_focal):
    check = FocalCheck(wrong_focal.camera, FocalCheckConfig(pairs=5))
    frame = wrong_focal.frames[0]
    assert all(check.add(frame.gray, frame.pose) is None for _ in range(50))
    assert check.pairs == [] and not check.done and check.frames == 50


def test_config_is_validated():
    with pytest.raises(ValueError, match=r'focal_check\.mode'):
        FocalCheckConfig(mode='fix')
    with pytest.raises(ValueError, match='pairs >= 5'):
        FocalCheckConfig(pairs=2)
    with pytest.raises(ValueError, match='min_baseline'):
        FocalCheckConfig(min_baseline=0.0)
    with pytest.raises(ValueError, match='lens_early_pairs >= 0'):
        FocalCheckConfig(lens_early_pairs=-1)
    assert FocalCheck(stress_config('translation').camera(), FocalCheckConfig(mode='off')).done


@pytest.mark.parametrize('mode', ['correct', 'warn'])
def test_evaluate_runs_the_check_and_corrects_when_asked(wrong_focal, mode):
    options = EvalOptions(
        frames=SIZE['frames'],
        keyframes=[30],
        single_view='simulated',
        width=320,
        height=240,
        params={'focal_check': {'pairs': PAIRS, 'mode': mode}},
    )
    result = evaluate_sequence(wrong_focal, ['single_view_simulated'], options, show_progress=False)
    entry = result.to_json()['focal_check']
    assert entry['verdict'] == 'disagrees' and entry['corrected'] == (mode == 'correct')
    assert entry['fitted_fx'] == pytest.approx(wrong_focal.gt_camera.fx, rel=0.03)
    fx = result.sequence.camera.fx
    assert fx == (pytest.approx(entry['fitted_fx']) if mode == 'correct' else wrong_focal.camera.fx)
    assert np.isfinite(result.records['single_view_simulated'].all.summary()['mae'])
    from depth_fusion_ros.evaluation.harness import results_document
    from depth_fusion_ros.evaluation.report import report_markdown

    report = report_markdown(results_document([result], ['single_view_simulated'], options))
    assert '## Focal length check' in report and '| disagrees | 288.8 |' in report
    assert f'| {fx:.1f} |' in report  # the focal length every method used, corrected or not


def test_the_node_runner_checks_off_the_callbacks_and_again_for_a_new_camera(wrong_focal):
    """``multi_view_node``'s runner: frames offered from the callbacks, the estimate computed on
    its thread and reported once with the camera it is for; a new camera is checked anew."""
    import time

    from depth_fusion_ros.camera import PinholeCamera
    from depth_fusion_ros.nodes.focal_check_runner import FocalCheckRunner
    from depth_fusion_ros.nodes.testing import RosHarness

    reports = []
    runner = FocalCheckRunner(FocalCheckConfig(pairs=PAIRS), lambda cam, est: reports.append((cam, est)))
    assert runner.status() == f'collecting (0 of {PAIRS} image pairs)'
    for frame in wrong_focal.frames:
        runner.offer(frame, wrong_focal.camera)
        time.sleep(0.05)  # a 20 Hz stream
        assert RosHarness.wait_for(lambda: not runner.pending, 30.0)  # its thread caught up, however loaded
    deadline = time.monotonic() + 30
    while not reports and time.monotonic() < deadline:
        time.sleep(0.05)
    assert len(reports) == 1 and reports[0][0] == wrong_focal.camera
    assert reports[0][1].verdict == 'disagrees' and runner.status().startswith('disagrees: fx 288.8 ->')
    other = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)
    runner.offer(wrong_focal.frames[0], other)
    assert runner.camera == other and runner.result is None and runner.status().startswith('collecting')
    runner.close()
    off = FocalCheckRunner(FocalCheckConfig(mode='off'), lambda *_: None)
    off.offer(wrong_focal.frames[0], wrong_focal.camera)
    assert off.status() == 'off' and off.camera is None


def test_a_busy_runner_queues_only_frames_far_from_the_last_it_queued(wrong_focal):
    """A runner whose thread is still busy with one sample is not handed the very next frames
    too (each far from the sample it took, not from one another), to skip on arrival while they
    fill its queue: the frames queued are a sample apart, and the thread takes each as one."""
    import threading

    from depth_fusion_ros.nodes.focal_check_runner import FocalCheckRunner
    from depth_fusion_ros.nodes.testing import RosHarness

    entered, gate = threading.Event(), threading.Event()

    class Held(FocalCheckRunner):
        def _feed(self, check, item):
            entered.set()
            assert gate.wait(30)
            return super()._feed(check, item)

    runner = Held(FocalCheckConfig(pairs=PAIRS), lambda *_: None)
    frames = wrong_focal.frames  # a sample every two frames
    runner.offer(frames[0], wrong_focal.camera)
    assert entered.wait(10)  # the thread holds frame 0
    for frame in frames[1:8]:  # 2 and 4 fill the queue; 6 finds it full and is dropped
        runner.offer(frame, wrong_focal.camera)
    held = runner.pending
    gate.set()
    assert RosHarness.wait_for(lambda: not runner.pending, 30.0)
    check = runner._check
    runner.close()
    assert held == 3 and runner.pending == 0
    taken = [[p.a.pose, p.b.pose] for p in check.pairs]
    assert check.frames == 3 and len(taken) == 2, (check.frames, len(taken))
    assert np.allclose(taken, [[frames[0].pose, frames[2].pose], [frames[2].pose, frames[4].pose]])


def test_an_unquoted_off_is_off():
    """YAML 1.1 reads ``mode: off`` (and ``--set focal_check.mode=off``) as false: still off."""
    from depth_fusion_ros.cli.overrides import parse_overrides
    from depth_fusion_ros.nodes.focal_check_runner import FOCAL_CHECK_PARAMETERS

    params = parse_overrides(['focal_check.mode=off'])
    assert params['focal_check']['mode'] is False
    assert FocalCheckConfig(**params['focal_check']).mode == 'off'
    spec = next(p for p in FOCAL_CHECK_PARAMETERS if p.name == 'focal_check.mode')
    assert spec.check(False) == 'off'
    from depth_fusion_ros.multiview.params import apply_overrides

    assert apply_overrides(FocalCheckConfig(), params['focal_check'], 'focal_check').mode == 'off'
    with pytest.raises(ValueError, match=r'focal_check\.pairs: expected an integer'):
        apply_overrides(FocalCheckConfig(), {'pairs': 'abc'}, 'focal_check')


def test_the_filter_takes_a_corrected_focal_length_without_starting_over(wrong_focal):
    """``DepthFilter.refocus``: the keyframe and its estimates are kept, made no more certain
    than the focal change, and the next frames move them towards the truth faster than the
    told focal length would ever let them."""
    from depth_fusion_ros.camera import PinholeCamera
    from depth_fusion_ros.multiview.filter import DepthFilter

    c = wrong_focal.camera
    true = PinholeCamera(c.width, c.height, c.fx / 1.1, c.fy / 1.1, c.cx, c.cy)

    def median_error(switch: bool) -> float:
        filt = DepthFilter(c)
        for i, frame in enumerate(wrong_focal.frames[:30]):
            if switch and i == 15:
                key, mu, var = filt.key, filt.key.state.mu.clone(), filt.key.state.var.clone()
                assert filt.refocus(true) and filt.camera == true and filt.key is key
                assert torch.equal(filt.key.state.mu, mu) and bool((filt.key.state.var >= var).all())
            filt.process(frame.gray, frame.pose)
        depth, gt = filt.result(wrong_focal.frames[29].pose).depth, wrong_focal.frames[29].depth
        ok = np.isfinite(depth) & np.isfinite(gt)
        return float(np.median(np.abs(np.log(depth[ok] / gt[ok]))))

    assert median_error(switch=True) < median_error(switch=False)
    filt = DepthFilter(c)
    assert not filt.refocus(PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx + 1, c.cy)) and filt.camera == c


def test_cli_check_focal_says_the_verdict_in_its_exit_status(tmp_path, capsys):
    """``depth-fusion check-focal``: a TUM folder and its rosbag2, without ground-truth depth;
    3 when the focal length disagrees, 0 when it agrees, 4 when there is too little motion."""
    from depth_fusion_ros.cli.main import main
    from depth_fusion_ros.data.synthetic import write_synthetic_sequence

    wrong = write_synthetic_sequence(tmp_path / 'wrong', stress_config('wrong_focal', **SIZE))
    right = write_synthetic_sequence(tmp_path / 'right', stress_config('translation', **SIZE))
    pairs = ['--pairs', str(PAIRS)]
    assert main(['check-focal', str(wrong), *pairs]) == 3
    assert 'camera_info says fx 288.8 px' in capsys.readouterr().out
    assert main(['check-focal', str(right), *pairs]) == 0
    assert 'agrees' in capsys.readouterr().out
    assert main(['convert', str(wrong), str(tmp_path / 'bag'), '--no-depth']) == 0
    assert main(['check-focal', str(tmp_path / 'bag'), *pairs]) == 3
    assert main(['check-focal', str(wrong), '--frames', '6']) == 4
    assert 'not enough motion to tell' in capsys.readouterr().err
    assert main(['check-focal', str(tmp_path / 'none')]) == 1


def test_the_node_warns_of_a_lens_whatever_the_focal_verdict():
    """``multi_view_node`` says the check's verdict once: a lens the pairs show and the node
    does not take (``focal_check.mode`` warn) is a warning (note ``lens_distortion``) also when
    the focal length itself agrees, and stays an info line without one (a lens taken:
    test_lens_correction.py)."""
    from types import SimpleNamespace

    from depth_fusion_ros.multiview.lens_fit import LensFit
    from depth_fusion_ros.nodes.multi_view_checks import CheckCorrections
    from depth_fusion_ros.nodes.stats import NodeStats

    warnings, infos = [], []
    node = SimpleNamespace(
        stats=NodeStats(warnings.append),
        get_logger=lambda: SimpleNamespace(info=infos.append),
        _lens_correctable=lambda: False,
    )
    camera = stress_config('translation', width=320, height=240).camera()
    plain = FocalEstimate(1.0, 0.005, 12, 4000, 'consistent', camera.fx, camera.fy)
    lens = FocalEstimate(
        1.0, 0.005, 12, 4000, 'consistent', camera.fx, camera.fy, LensFit(-0.09, 0.01, 0.6, 0, 12)
    )
    CheckCorrections._on_focal_estimate(node, camera, plain)
    assert len(infos) == 1 and not warnings and node.stats.snapshot().noted == {}
    CheckCorrections._on_focal_estimate(node, camera, lens)
    assert node.stats.snapshot().noted == {'lens_distortion': 1}
    assert len(warnings) == 1 and 'lens distortion k1 -0.09' in warnings[0] and len(infos) == 1
