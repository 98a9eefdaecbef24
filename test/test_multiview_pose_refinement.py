"""Poses refined against the filter keyframe's image (``multiview/pose_refinement.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from depth_fusion_ros.data.synthetic import render_sequence, stress_config
from depth_fusion_ros.multiview import pose_refinement
from depth_fusion_ros.multiview.filter import KEYFRAME, DepthFilter
from depth_fusion_ros.multiview.filter_config import FilterConfig
from depth_fusion_ros.multiview.pose_refinement import PoseRefiner

#: A SLAM's keyframe stream (15 cm and 6.7 deg between frames), with a SLAM's pose noise.
STREAM = {'frames': 24, 'seed': 301}
SLAM_NOISE = {'pose_noise_m': 0.005, 'pose_noise_deg': 0.3, 'gain_sigma': 0.1}


@pytest.fixture(scope='module')
def exact():
    return render_sequence(stress_config('keyframes', **STREAM))


@pytest.fixture(scope='module')
def noisy():
    """The same images as ``exact`` (same seed), told poses with independent jitter."""
    return render_sequence(stress_config('keyframes', **STREAM, **SLAM_NOISE))


def _turn_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude())


def _relative_errors(told, truth, frames: range) -> tuple[list[float], list[float]]:
    """Relative rotation error (deg) of each frame to the one before it: told and refined, the
    keyframe at its true pose."""
    refiner = PoseRefiner(told.camera, 0.5, 0.01, 300)
    before, after = [], []
    for i in frames:
        key, frame = truth.frames[i - 1], told.frames[i]
        refiner.keyframe(key.gray, key.pose)
        refined = refiner.refine(frame.gray, frame.pose, 2.0)
        assert refined is not None, f'frame {i} kept its told pose'
        true_rel = np.linalg.inv(key.pose) @ truth.frames[i].pose
        before.append(_turn_deg(np.linalg.inv(key.pose) @ frame.pose, true_rel))
        after.append(_turn_deg(np.linalg.inv(key.pose) @ refined, true_rel))
    return before, after


def test_a_noisy_pose_is_turned_towards_the_truth(exact, noisy):
    before, after = _relative_errors(noisy, exact, range(1, 13))
    assert np.median(before) > 0.2
    assert np.median(after) < 0.5 * np.median(before)
    assert sum(a < b for a, b in zip(after, before, strict=True)) >= 9


def test_an_exact_pose_stays_where_it_is(exact):
    _, after = _relative_errors(exact, exact, range(1, 9))
    assert np.median(after) < 0.1
    assert max(after) < 0.3


def test_a_frame_without_corners_keeps_its_told_pose(exact):
    refiner = PoseRefiner(exact.camera, 0.5, 0.01, 300)
    refiner.keyframe(exact.frames[0].gray, exact.frames[0].pose)
    blank = np.full_like(exact.frames[1].gray, 0.5)
    assert refiner.refine(blank, exact.frames[1].pose, 2.0) is None
    f = DepthFilter(exact.camera)
    f.process(exact.frames[0].gray, exact.frames[0].pose)
    f.process(blank, exact.frames[1].pose)
    assert (f.stats.refined, f.stats.kept_told) == (0, 1)
    assert np.array_equal(f.used_pose(exact.frames[1].pose), exact.frames[1].pose)


def _published(sequence, config: FilterConfig) -> tuple[float, float, DepthFilter]:
    """Mean share of published estimates more than 10 % off their keyframe's median error, and
    mean density, over the stream's frames (the filter's estimate in each frame)."""
    f = DepthFilter(sequence.camera, config)
    bad, density = [], []
    for i, frame in enumerate(sequence.frames):
        f.process(frame.gray, frame.pose)
        r = f.result(frame.pose)
        gt = sequence.gt_depth_working(i)
        ok = np.isfinite(r.depth) & (gt > 0)
        density.append(ok.mean())
        if i > 0 and ok.sum() > 100:
            e = np.log(r.depth[ok] / gt[ok])
            bad.append(float(np.mean(np.abs(e - np.median(e)) > 0.1)))
    return float(np.mean(bad)), float(np.mean(density)), f


def test_the_filter_measures_more_and_better_with_refined_poses(noisy):
    told_bad, told_density, _ = _published(noisy, FilterConfig(refine_poses=False))
    bad, density, f = _published(noisy, FilterConfig())
    assert told_bad > 0.3
    assert bad < 0.5 * told_bad
    assert density > 1.5 * told_density
    assert f.stats.refined >= 0.8 * (len(noisy.frames) - 1)
    assert f.stats.refined + f.stats.kept_told <= len(noisy.frames) - 1


def test_a_result_asked_by_the_told_pose_is_read_at_the_refined_one(noisy):
    f = DepthFilter(noisy.camera)
    switched = None
    for i, frame in enumerate(noisy.frames):
        if f.process(frame.gray, frame.pose) == KEYFRAME and i > 0 and f.stats.refined:
            switched = frame.pose
            break
    assert switched is not None, 'no refined frame became the keyframe'
    used = f.used_pose(switched)
    assert not np.allclose(used, switched)
    assert np.array_equal(used, f.key.pose)
    here, asked = f.result(), f.result(switched)
    assert np.isfinite(here.depth).sum() > 0
    assert np.array_equal(np.isfinite(here.depth), np.isfinite(asked.depth))
    assert np.allclose(here.depth[np.isfinite(here.depth)], asked.depth[np.isfinite(asked.depth)])
    unknown = np.eye(4)
    assert np.array_equal(f.used_pose(unknown), unknown)


@pytest.mark.parametrize(
    'field, value',
    [
        ('refine_sigma_deg', 0.0),
        ('refine_sigma_m', -0.01),
        ('refine_corners', 10),
        ('refine_sigma_deg', 90.0),
    ],
)
def test_bad_refinement_settings_are_named(field, value):
    with pytest.raises(ValueError, match=f'filter.{field}'):
        FilterConfig(**{field: value}).validate()


def test_a_keyframe_without_corners_refines_nothing_and_fails_nothing(exact):
    """A texture-less keyframe has no corners to track: the frames after it keep their told
    poses (counted), and the filter goes on."""
    blank = np.full_like(exact.frames[0].gray, 0.5)
    f = DepthFilter(exact.camera)
    assert f.process(blank, exact.frames[0].pose) == KEYFRAME
    f.process(exact.frames[1].gray, exact.frames[1].pose)
    assert (f.stats.refined, f.stats.kept_told) == (0, 1)
    assert np.array_equal(f.used_pose(exact.frames[1].pose), exact.frames[1].pose)


@pytest.fixture
def levels(monkeypatch) -> list[int]:
    """The pyramid levels of every Lucas-Kanade call the refiner makes, in order."""
    seen: list[int] = []
    lucas_kanade = pose_refinement.cv2.calcOpticalFlowPyrLK

    def spy(*args, **kwargs):
        seen.append(kwargs['maxLevel'])
        return lucas_kanade(*args, **kwargs)

    monkeypatch.setattr(pose_refinement.cv2, 'calcOpticalFlowPyrLK', spy)
    return seen


def test_following_frames_go_on_from_the_previous_frames_tracks(levels):
    """After a keyframe's first frame, each frame starts its tracks where the previous one found
    them (one pyramid level above the image instead of three: a third of the tracking's cost),
    and it turns the
    noisy poses towards the truth as well as tracking from the told pose alone does. A frame
    that keeps its told pose, and a new keyframe, start over from the told pose."""
    stream = {'frames': 12, 'seed': 301}
    truth = render_sequence(stress_config('rotation', **stream))
    told = render_sequence(stress_config('rotation', **stream, **SLAM_NOISE))
    key = truth.frames[0]
    chained = PoseRefiner(told.camera, 0.5, 0.01, 300)
    chained.keyframe(key.gray, key.pose)
    before, after, alone, chained_levels = [], [], [], []
    for i in range(1, 10):
        frame, true_rel = told.frames[i], np.linalg.inv(key.pose) @ truth.frames[i].pose
        levels.clear()
        refined = chained.refine(frame.gray, frame.pose, 2.0)
        assert refined is not None, f'frame {i} kept its told pose'
        chained_levels.append(levels[0])
        fresh = PoseRefiner(told.camera, 0.5, 0.01, 300)
        fresh.keyframe(key.gray, key.pose)
        on_its_own = fresh.refine(frame.gray, frame.pose, 2.0)
        before.append(_turn_deg(np.linalg.inv(key.pose) @ frame.pose, true_rel))
        after.append(_turn_deg(np.linalg.inv(key.pose) @ refined, true_rel))
        alone.append(_turn_deg(np.linalg.inv(key.pose) @ on_its_own, true_rel))
    full, chain = pose_refinement.LK_LEVELS, pose_refinement.CHAINED_LEVELS
    # The first frame from the told pose; most others from the previous frame's tracks (a frame
    # that kept fewer than half of the keyframe's corners makes the next one start over).
    assert chained_levels[0] == full and chained_levels.count(chain) >= 5
    assert np.median(after) < 0.5 * np.median(before)
    assert np.median(after) <= np.median(alone) + 0.02
    # A frame without corners tries the previous frame's tracks, then all from the told pose,
    # and keeps its told pose; the next starts over, as after a keyframe. (The keyframe again
    # and its first frame, so that the previous frame's tracks hold more than half the corners.)
    chained.keyframe(key.gray, key.pose)
    assert chained.refine(told.frames[1].gray, told.frames[1].pose, 2.0) is not None
    levels.clear()
    assert chained.refine(np.full_like(key.gray, 0.5), told.frames[2].pose, 2.0) is None
    assert levels == [chain, chain, full, full]
    assert chained.refine(told.frames[11].gray, told.frames[11].pose, 2.0) is not None
    assert levels[4:] == [full, full]
    chained.keyframe(truth.frames[11].gray, truth.frames[11].pose)
    chained.refine(told.frames[10].gray, told.frames[10].pose, 2.0)
    assert levels[-2:] == [full] * 2


def test_a_keyframe_streams_long_steps_track_from_the_told_pose(exact, noisy, levels):
    """A SLAM keyframe stream's frames are 15 cm apart: from the previous frame's tracks a
    point at half the scene depth would start 22 px off, beyond one pyramid level. Each frame
    tracks from the told pose with every level, and is refined."""
    refiner = PoseRefiner(noisy.camera, 0.5, 0.01, 300)
    refiner.keyframe(exact.frames[0].gray, exact.frames[0].pose)
    for frame in noisy.frames[1:4]:
        assert refiner.refine(frame.gray, frame.pose, 2.0) is not None
    assert levels == [pose_refinement.LK_LEVELS] * 6
