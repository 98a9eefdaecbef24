"""The time offset check: poses stamped 20 ms off their images are found from the images (issue
11's "a multi-view depth that never misleads": a camera and pose source out of sync), poses in
sync are not flagged, smooth motion and noisy poses do not fake an offset, ``evaluate`` re-reads
the poses when asked, and ``depth-fusion check-sync`` says the verdict in its exit status."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.geometry import relative_pose, rotation_angle
from depth_fusion_ros.multiview.time_offset_check import (
    TimeOffsetCheck,
    TimeOffsetCheckConfig,
    check_stream,
    shift_in_time,
)
from depth_fusion_ros.pose_curve import interpolate_poses_cubic

#: 240x180 over a 1 m sweep by a shaking hand in 60 frames at 30 Hz: a pair every two frames.
SIZE = {'width': 240, 'height': 180, 'frames': 60, 'seed': 5}


def _stream(offset: float, **overrides):
    return render_sequence(stress_config('time_offset', **SIZE, pose_time_offset=offset, **overrides))


@pytest.fixture(scope='module')
def late():
    """Every told pose is the camera's pose 20 ms after its image's stamp."""
    return _stream(0.02)


def _check(sequence, **config):
    check = check_stream(sequence.camera, sequence.frames, TimeOffsetCheckConfig(**config))
    return check.result, check


@pytest.mark.parametrize('offset', [0.02, -0.02])
def test_poses_stamped_20_ms_off_are_found(late, offset):
    sequence = late if offset > 0 else _stream(offset)
    estimate, check = _check(sequence, early_pairs=0)  # the last look only: all 20 pairs
    assert estimate is not None and check.done and estimate.pairs == 20
    assert estimate.verdict == 'disagrees', estimate.message()
    # The told pose of an image is the camera's pose `offset` later: reading it `offset` earlier fits.
    assert estimate.offset == pytest.approx(-offset, abs=0.003) and estimate.stderr < 0.004
    assert estimate.fitted == estimate.offset and estimate.sharpness > 0.1
    message = estimate.message()
    assert 'out of sync' in message and f'pose_time_offset {-offset:.3f}' in message
    assert check.add(sequence.frames[0].gray, 99.0, sequence.frames[0].pose) is None  # once


def test_the_early_look_ends_the_check_only_where_the_pairs_settle_it(late):
    """At ``early_pairs`` (8) the check ends on an offset sure by three standard errors, or on
    motion so smooth that no offset matters; poses in sync wait for all 20 pairs, so the early
    look never says they agree on less evidence than the last one."""
    early, check = _check(late)
    assert early is not None and early.pairs == 8 and early.verdict == 'disagrees', early.message()
    assert early.offset == pytest.approx(-0.02, abs=0.003) and abs(early.offset) - 3 * early.stderr >= 0.015
    assert check.add(late.frames[0].gray, 99.0, late.frames[0].pose) is None  # once
    flat, _ = _check(render_sequence(stress_config('translation', **SIZE, pose_time_offset=0.02)))
    assert flat is not None and flat.pairs == 8 and flat.verdict == 'unobservable', flat.message()
    assert flat.sharpness < 0.005 and flat.flat
    # A flat fit's offset is wherever the noise put it: said as flat, not as a number to copy.
    assert 'too smooth' in flat.message() and 'ms' not in flat.message(), flat.message()
    assert flat.fit_phrase() == 'flat over 8 pairs' and early.fit_phrase().startswith('-20 +- ')
    in_sync, _ = _check(_stream(0.0))
    assert in_sync is not None and in_sync.pairs == 20 and in_sync.verdict == 'consistent', in_sync.message()
    with pytest.raises(ValueError, match='early_pairs'):
        TimeOffsetCheckConfig(early_pairs=3)


def test_poses_in_sync_are_not_flagged():
    estimate, _ = _check(_stream(0.0))
    assert estimate is not None and estimate.verdict == 'consistent', estimate.message()
    assert abs(estimate.offset) <= 0.002 and 'agrees' in estimate.message()


def test_smooth_motion_leaves_the_offset_unobservable():
    """A sweep at constant speed: every relative pose is the same whenever it is read, so the
    offset neither shows in the images nor matters to the depth."""
    smooth = render_sequence(stress_config('translation', **SIZE, pose_time_offset=0.02))
    estimate, _ = _check(smooth)
    assert estimate is not None and estimate.verdict == 'unobservable', estimate.message()
    assert 'kept, unchecked' in estimate.message()


def test_noisy_poses_do_not_fake_an_offset():
    """4 mm and 0.25 deg of independent pose noise per frame on the shaking hand, in sync."""
    estimate, _ = _check(_stream(0.0, pose_noise_m=0.004, pose_noise_deg=0.25))
    assert estimate is not None and estimate.verdict != 'disagrees', estimate.message()


def test_a_camera_that_stands_still_gives_no_pairs(late):
    check = TimeOffsetCheck(late.camera, TimeOffsetCheckConfig(pairs=5))
    frame = late.frames[0]
    assert all(check.add(frame.gray, 0.1 * i, frame.pose) is None for i in range(50))
    assert check.pairs == 0 and not check.done and check.frames == 50


def test_shift_in_time_follows_the_cubic_inside_and_extrapolates_at_the_ends(late):
    stamps = np.array([f.stamp for f in late.frames])
    poses = np.stack([f.pose for f in late.frames])
    assert np.array_equal(shift_in_time(stamps, poses, 0.0), poses)
    shifted = shift_in_time(stamps, poses, 0.01)
    inside, ok = interpolate_poses_cubic(stamps - stamps[0], poses, stamps[:-1] + 0.01 - stamps[0])
    assert ok.all() and np.allclose(shifted[:-1], inside)
    # The last frame moves on along its last step, by 10 ms of its 33 ms.
    step, end = relative_pose(poses[-2], poses[-1]), relative_pose(poses[-1], shifted[-1])
    assert np.allclose(
        shifted[-1][:3, 3] - poses[-1][:3, 3], 0.3 * (poses[-1][:3, 3] - poses[-2][:3, 3]), atol=1e-6
    )
    assert rotation_angle(end[:3, :3]) == pytest.approx(0.3 * rotation_angle(step[:3, :3]), rel=1e-4)
    first = shift_in_time(stamps, poses, -0.01)[0]  # and the first one back along its first step
    assert np.allclose(first[:3, 3] - poses[0][:3, 3], 0.3 * (poses[0][:3, 3] - poses[1][:3, 3]), atol=1e-6)


def test_config_is_validated():
    with pytest.raises(ValueError, match=r'time_offset_check\.mode'):
        TimeOffsetCheckConfig(mode='fix')
    with pytest.raises(ValueError, match='pairs >= 5'):
        TimeOffsetCheckConfig(pairs=2)
    with pytest.raises(ValueError, match='max_offset'):
        TimeOffsetCheckConfig(max_offset=5.0)
    with pytest.raises(ValueError, match='threshold < max_offset'):
        TimeOffsetCheckConfig(threshold=0.2)
    assert TimeOffsetCheckConfig(mode=False).mode == 'off'  # YAML's unquoted `off`


@pytest.mark.parametrize('mode', ['correct', 'warn'])
def test_evaluate_runs_the_check_and_rereads_the_poses_when_asked(late, mode):
    """``evaluate`` runs the check first; in correct mode the poses are read again from the pose
    source as recorded (``Sequence.pose_stream``), where a source that only stamped its samples
    off gives the exact poses back."""
    from depth_fusion_ros.evaluation.context import EvalOptions
    from depth_fusion_ros.evaluation.harness import evaluate_sequence, results_document
    from depth_fusion_ros.evaluation.report import report_markdown

    options = EvalOptions(
        frames=SIZE['frames'],
        keyframes=[30],
        single_view='simulated',
        width=SIZE['width'],
        height=SIZE['height'],
        params={'time_offset_check': {'mode': mode}},
    )
    result = evaluate_sequence(late, ['single_view_simulated'], options, show_progress=False)
    entry = result.to_json()['time_offset_check']
    assert entry['verdict'] == 'disagrees' and entry['corrected'] == (mode == 'correct')
    assert entry['fitted_offset'] == pytest.approx(-0.02, abs=0.003)
    # The poses every method used, against the camera's true poses (the stream in sync).
    truth = _stream(0.0)

    def error_mm(sequence) -> float:
        inner = range(5, SIZE['frames'] - 5)
        return 1000 * float(
            np.median(
                [np.linalg.norm(sequence.frames[i].pose[:3, 3] - truth.frames[i].pose[:3, 3]) for i in inner]
            )
        )

    before, used = error_mm(late), error_mm(result.sequence)
    if mode == 'correct':  # read again from the pose source's own samples: the true poses
        assert before > 5 and used < 1e-6, (used, before)
    else:
        assert used == before
    report = report_markdown(results_document([result], ['single_view_simulated'], options))
    assert '## Time offset check' in report and '| disagrees | -20 +- ' in report


def test_the_node_runner_checks_off_the_callbacks(late):
    """``multi_view_node``'s runner: every frame's pose queued, samples' images too, the
    estimate computed on its thread, reported once; the correction only in correct mode."""
    import time

    from depth_fusion_ros.nodes.testing import RosHarness
    from depth_fusion_ros.nodes.time_offset_check_runner import TimeOffsetCheckRunner

    for mode in ('correct', 'warn'):
        reports = []
        runner = TimeOffsetCheckRunner(
            TimeOffsetCheckConfig(mode=mode), 0.0, lambda cam, est, out=reports: out.append((cam, est))
        )
        assert runner.status() == 'collecting (0 of 20 image pairs)' and runner.correction == 0.0
        for frame in late.frames:
            runner.offer(frame, late.camera)
            time.sleep(0.03)  # a 30 Hz stream
            # its thread caught up, however loaded
            assert RosHarness.wait_for(lambda r=runner: not r.pending, 30.0)
        deadline = time.monotonic() + 30
        while not reports and time.monotonic() < deadline:
            time.sleep(0.05)
        runner.close()
        assert len(reports) == 1 and reports[0][1].verdict == 'disagrees', runner.status()
        assert runner.status().startswith('disagrees: -20 +- ')
        expected = pytest.approx(-0.02, abs=0.003) if mode == 'correct' else 0.0
        assert runner.correction == expected


def test_a_busy_runner_makes_grey_images_only_for_the_samples_it_will_take(late):
    """While the runner's thread is busy with one sample, the callbacks still queue every
    frame's pose, but a grey image only for frames a sample apart from the last one queued
    with one: the thread takes every grey image it is handed as a sample."""
    import threading

    from depth_fusion_ros.nodes.testing import RosHarness
    from depth_fusion_ros.nodes.time_offset_check_runner import TimeOffsetCheckRunner

    entered, gate = threading.Event(), threading.Event()
    fed: list[tuple[bool, bool]] = []  # (a grey image came with it, the check wanted it as a sample)

    class Held(TimeOffsetCheckRunner):
        def _feed(self, check, item):
            fed.append((item[0] is not None, check.wants(item[1], item[2])))
            entered.set()
            assert gate.wait(30)
            return super()._feed(check, item)

    # A sample every 2-3 frames (1.5-2 cm a frame), far from done after 25 frames.
    config = TimeOffsetCheckConfig(min_baseline=0.035, min_rotation_deg=45.0, early_pairs=0)
    runner = Held(config, 0.0, lambda *_: None)
    runner.offer(late.frames[0], late.camera)
    assert entered.wait(10)  # the thread holds frame 0
    for frame in late.frames[1:25]:
        runner.offer(frame, late.camera)
    gate.set()
    assert RosHarness.wait_for(lambda: not runner.pending, 30.0)
    runner.close()
    assert len(fed) == 25  # every pose reached the thread
    grey = [wanted for with_grey, wanted in fed if with_grey]
    assert 8 <= len(grey) <= 13 and all(grey), fed  # each grey image was a sample the thread took


def test_a_check_waits_for_the_keyframe_path_before_each_sample(late):
    """The check's thread does a sample's work (ORB, matching) only once the node's keyframe
    path has nothing in hand (``busy``), and never waits more than MAX_YIELD_S a sample under a
    load that does not let up; a pose alone is not held back."""
    import threading
    import time

    from depth_fusion_ros.nodes.check_runner import MAX_YIELD_S
    from depth_fusion_ros.nodes.testing import RosHarness
    from depth_fusion_ros.nodes.time_offset_check_runner import TimeOffsetCheckRunner

    busy = threading.Event()
    fed: list[tuple[bool, bool]] = []  # (a sample, the keyframe path busy when its work began)

    class Recording(TimeOffsetCheckRunner):
        def _feed(self, check, item):
            fed.append((item[0] is not None, busy.is_set()))
            return super()._feed(check, item)

    # A sample every 2-3 frames (1.5-2 cm a frame): the frames between are poses alone.
    config = TimeOffsetCheckConfig(min_baseline=0.035, min_rotation_deg=45.0, early_pairs=0)
    runner = Recording(config, 0.0, lambda *_: None)
    runner.busy = busy.is_set
    busy.set()
    runner.offer(late.frames[0], late.camera)  # the first frame is a sample
    time.sleep(MAX_YIELD_S / 5)
    assert fed == [] and runner.pending == 1  # it waits for the keyframe path
    busy.clear()
    assert RosHarness.wait_for(lambda: not runner.pending, 10.0)
    assert fed == [(True, False)]
    busy.set()  # a load that never lets up: each sample still comes within MAX_YIELD_S
    started = time.monotonic()
    for frame in late.frames[1:8]:
        runner.offer(frame, late.camera)
    assert RosHarness.wait_for(lambda: not runner.pending, 30.0)
    runner.close()
    samples = sum(sample for sample, _ in fed[1:])
    assert 1 <= samples < len(fed[1:]) and all(was_busy for _, was_busy in fed[1:])  # poses too
    assert time.monotonic() - started < samples * MAX_YIELD_S + 5.0
    assert runner.waited >= samples * MAX_YIELD_S * 0.9  # each later sample waited the whole cap
    # ... and only the samples: a pose alone would have added another MAX_YIELD_S
    assert runner.waited < samples * MAX_YIELD_S + MAX_YIELD_S / 5 + 0.3
    assert 0.0 < runner.cpu < time.monotonic() - started + 1.0  # its own thread's CPU, counted


def test_cli_check_sync_says_the_verdict_in_its_exit_status(tmp_path, late, capsys):
    """``depth-fusion check-sync``: a TUM folder and its rosbag2, without ground-truth depth; 3
    out of sync, 0 in sync (also once told the offset), 4 when it cannot tell. ``synth`` takes
    an option given as its default over the preset's (``--pose-time-offset 0``)."""
    from depth_fusion_ros.cli.main import main

    common = ['--width', '240', '--height', '180', '--frames', '60', '--seed', '5', '--quiet']
    assert main(['synth', str(tmp_path / 'late'), '--stress', 'time_offset', *common]) == 0
    assert (
        main(['synth', str(tmp_path / 'sync'), '--stress', 'time_offset', '--pose-time-offset', '0', *common])
        == 0
    )
    size = ['--width', '240', '--height', '180']
    assert main(['check-sync', str(tmp_path / 'late'), *size]) == 3
    assert 'pose_time_offset -0.020 fits them' in capsys.readouterr().out
    assert main(['check-sync', str(tmp_path / 'sync'), *size]) == 0
    assert 'agrees' in capsys.readouterr().out
    assert main(['check-sync', str(tmp_path / 'late'), *size, '--pose-time-offset', '-0.02']) == 0
    assert main(['convert', str(tmp_path / 'late'), str(tmp_path / 'bag'), '--no-depth']) == 0
    assert main(['check-sync', str(tmp_path / 'bag'), *size]) == 3
    assert main(['check-sync', str(tmp_path / 'late'), '--frames', '6']) == 4
    assert 'not enough motion to tell' in capsys.readouterr().err
    assert main(['check-sync', str(tmp_path / 'none')]) == 1
