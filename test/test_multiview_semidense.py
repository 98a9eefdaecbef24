"""Semi-dense multi-view depth: accuracy on exact synthetic scenes, scores, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.geometry import PoseError, make_pose
from depth_fusion_ros.multiview.neighbours import select_neighbours
from depth_fusion_ros.multiview.plane_scene import Plane, default_scene, render_planes
from depth_fusion_ros.multiview.semidense import (
    MultiViewConfig,
    estimate_semidense,
    select_best_fraction,
)

CAMERA = PinholeCamera(320, 240, 260.0, 260.0, 159.5, 119.5)
#: Neighbour offsets (m) around a keyframe at the origin: several directions, 6-8 cm.
OFFSETS = ((0.08, 0.0, 0.0), (-0.08, 0.0, 0.0), (0.0, 0.06, 0.0), (0.05, -0.05, 0.03))
#: Texture resolution near the pixel footprint at the 3 m wall (no aliasing).
SCENE = default_scene(texel=0.008)


pytestmark = pytest.mark.usefixtures('one_torch_thread')


def translated(offset: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = offset
    return T


def render_views(planes: list[Plane], poses: list[np.ndarray], camera: PinholeCamera = CAMERA):
    images = [render_planes(planes, camera, T) for T in poses]
    return [g for g, _ in images], [d for _, d in images]


@pytest.fixture(scope='module')
def planes_views():
    """Keyframe at the origin and four translated neighbours looking at the default scene."""
    poses = [np.eye(4)] + [translated(o) for o in OFFSETS]
    grays, depths = render_views(SCENE, poses)
    return grays, depths, poses


@pytest.fixture(scope='module')
def four_view_result(planes_views):
    grays, _, poses = planes_views
    return estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA)


def relative_error(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.abs(estimate[mask] - truth[mask]) / truth[mask]


def test_textured_planes_match_ground_truth(planes_views, four_view_result):
    _, depths, _ = planes_views
    result = four_view_result
    valid = result.valid
    assert result.density > 0.08
    assert np.median(relative_error(result.depth, depths[0], valid)) < 0.02
    selected = select_best_fraction(result, 0.25)
    assert selected.sum() == pytest.approx(0.25 * valid.sum(), abs=1)
    assert np.median(relative_error(result.depth, depths[0], selected)) < 0.015
    # Every map is NaN exactly where there is no estimate.
    for name in ('depth_std', 'photometric_score', 'geometric_score', 'score', 'cost'):
        assert np.array_equal(np.isfinite(getattr(result, name)), valid), name
    assert np.allclose(result.score[valid], (result.photometric_score * result.geometric_score)[valid])


def test_single_neighbour_still_works(planes_views):
    grays, depths, poses = planes_views
    result = estimate_semidense(grays[0], poses[0], grays[1:2], poses[1:2], CAMERA)
    assert result.density > 0.05
    assert np.median(relative_error(result.depth, depths[0], result.valid)) < 0.03


def test_textureless_area_gets_no_confident_estimate():
    # Left half: textured wall at 2 m; right half: a flat grey board in front of it.
    planes = [
        Plane((0.0, 0.0, 1.0), 2.0, seed=4, texture_scale=0.008),
        Plane((0.0, 0.0, 1.0), 1.2, textured=False, bounds=(0.0, 5.0, -5.0, 5.0)),
    ]
    poses = [np.eye(4)] + [translated(o) for o in OFFSETS]
    grays, depths = render_views(planes, poses)
    flat = np.zeros(depths[0].shape, dtype=bool)
    flat[:, 170:] = True  # the board starts at the optical axis (u = cx); keep clear of its edge
    semi = estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA)
    assert not semi.candidates[flat].any(), 'a texture-less area has no gradient: no candidate'
    dense = estimate_semidense(
        grays[0], poses[0], grays[1:], poses[1:], CAMERA, MultiViewConfig(all_pixels=True)
    )
    textured = dense.valid & ~flat
    flat_scored = dense.valid & flat
    assert textured.sum() > 0.3 * (~flat).sum()
    # Where the flat board got any estimate its score is far below the textured wall's.
    if flat_scored.any():
        assert np.median(dense.score[flat_scored]) < 0.1 * np.median(dense.score[textured])
    selected = select_best_fraction(dense, 0.25)
    assert not (selected & flat).any()


def test_pure_rotation_gives_low_geometric_score(planes_views, four_view_result):
    grays, _, poses = planes_views
    rotations = [make_pose((0.0, 0.0, 0.0), q) for q in ((0, 0.02, 0, 1), (0.02, 0, 0, 1), (0, -0.02, 0, 1))]
    rot_grays, _ = render_views(SCENE, rotations)
    rotated = estimate_semidense(grays[0], poses[0], rot_grays, rotations, CAMERA)
    high = np.median(four_view_result.geometric_score[four_view_result.valid])
    if rotated.valid.any():
        assert np.max(rotated.geometric_score[rotated.valid]) < 1e-2 * high


def test_low_parallax_scores_below_high_parallax(planes_views, four_view_result):
    grays, _, poses = planes_views
    near_poses = [translated(tuple(0.1 * c for c in o)) for o in OFFSETS]
    near_grays, _ = render_views(SCENE, near_poses)
    low = estimate_semidense(grays[0], poses[0], near_grays, near_poses, CAMERA)
    high = four_view_result
    assert np.median(low.geometric_score[low.valid]) < 0.2 * np.median(high.geometric_score[high.valid])


def test_chunking_bounds_memory_without_changing_the_result(planes_views):
    grays, _, poses = planes_views
    config = MultiViewConfig(num_samples=48, max_candidate_fraction=0.02)
    small = MultiViewConfig(num_samples=48, max_candidate_fraction=0.02, chunk_elements=1 << 16)
    a = estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA, config)
    b = estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA, small)
    assert np.array_equal(a.valid, b.valid)
    np.testing.assert_allclose(a.depth[a.valid], b.depth[b.valid], rtol=1e-5)


def test_many_samples_run_in_bounded_chunks(planes_views):
    grays, depths, poses = planes_views
    config = MultiViewConfig(num_samples=512, chunk_elements=1 << 18, max_candidate_fraction=0.01)
    result = estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA, config)
    assert result.valid.sum() > 0.5 * result.candidates.sum()
    assert np.median(relative_error(result.depth, depths[0], result.valid)) < 0.03


@pytest.mark.parametrize(
    ('bad', 'message'),
    [
        (np.full((4, 4), np.nan), 'neighbour 0 pose: contains NaN'),
        (np.diag([2.0, 1.0, 1.0, 1.0]), 'neighbour 0 pose: rotation is not orthonormal'),
        (np.eye(3), 'neighbour 0 pose: expected a 4x4'),
    ],
)
def test_bad_poses_raise_clear_errors(planes_views, bad, message):
    grays, _, poses = planes_views
    with pytest.raises(PoseError, match=message):
        estimate_semidense(grays[0], poses[0], [grays[1]], [bad], CAMERA)


def test_bad_inputs_raise_clear_errors(planes_views):
    grays, _, poses = planes_views
    with pytest.raises(ValueError, match='keyframe pose'):
        estimate_semidense(grays[0], np.full((4, 4), np.nan), grays[1:], poses[1:], CAMERA)
    with pytest.raises(ValueError, match='at least one neighbour'):
        estimate_semidense(grays[0], poses[0], [], [], CAMERA)
    with pytest.raises(ValueError, match='neighbour 1 image: expected a grey image of 240x320'):
        estimate_semidense(grays[0], poses[0], [grays[1], grays[2][:50]], poses[1:3], CAMERA)
    with pytest.raises(ValueError, match='2 neighbour images but 1 neighbour poses'):
        estimate_semidense(grays[0], poses[0], grays[1:3], poses[1:2], CAMERA)
    nan_image = grays[1].copy()
    nan_image[3, 3] = np.nan
    with pytest.raises(ValueError, match='neighbour 0 image: grey image contains NaN'):
        estimate_semidense(grays[0], poses[0], [nan_image], poses[1:2], CAMERA)
    with pytest.raises(ValueError, match='min_depth < max_depth'):
        estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA, MultiViewConfig(min_depth=20.0))
    with pytest.raises(ValueError, match='patch must be one of'):
        estimate_semidense(grays[0], poses[0], grays[1:], poses[1:], CAMERA, MultiViewConfig(patch='disc'))


def test_rendered_sequence_high_parallax(synthetic_sequence):
    """The synthetic room renderer: stage-1 points within 2 % median on a keyframe."""
    seq = synthetic_sequence
    key = 12
    chosen = select_neighbours(seq.poses, key, 4, 'offline', seq.camera)
    frames = seq.frames
    result = estimate_semidense(
        frames[key].gray,
        frames[key].pose,
        [frames[i].gray for i in chosen],
        [frames[i].pose for i in chosen],
        seq.camera,
        neighbours=chosen,
    )
    gt = seq.gt_depth_working(key)
    selected = select_best_fraction(result, 0.25) & np.isfinite(gt)
    assert result.neighbours == tuple(chosen)
    assert result.density > 0.05
    assert selected.mean() > 0.01
    assert np.median(relative_error(result.depth, gt, selected)) < 0.02


def test_pixels_leaving_most_neighbours_get_no_estimate(planes_views):
    grays, _, poses = planes_views
    # Three of four neighbours 0.4 m to the right: the keyframe's left border (~35 px at the
    # 3 m wall, more for nearer surfaces) leaves their images; only one neighbour still sees it.
    far = [translated((0.4, 0.0, 0.0)), translated((0.4, 0.05, 0.0)), translated((0.45, -0.05, 0.0))]
    far_grays, _ = render_views(SCENE, far)
    result = estimate_semidense(
        grays[0], poses[0], [grays[1], *far_grays], [poses[1], *far], CAMERA, MultiViewConfig(max_depth=4.0)
    )
    assert not result.valid[:, :30].any()
    assert result.valid[:, 60:].sum() > 1000


@pytest.mark.parametrize(
    'config',
    [
        MultiViewConfig(),  # more pixels pass min_gradient than the cap: the cap-th gradient is the threshold
        MultiViewConfig(min_gradient=0.15),  # fewer pass: min_gradient is the threshold
        MultiViewConfig(max_candidate_fraction=0.03, chunk_elements=1 << 16),  # several chunks
        MultiViewConfig(patch='cross', descriptor_channels=0, num_samples=32, refine_samples=2),
    ],
    ids=['capped', 'thresholded', 'chunked', 'cross_patch'],
)
def test_the_capturable_sweep_gives_the_eager_estimates(planes_views, config):
    """The sweep a CUDA graph records (a fixed number of pixels, the candidates chosen on the
    device without reading back) must give the eager sweep's candidates and estimates; run
    here eagerly on the CPU, the same code."""
    from depth_fusion_ros.multiview import semidense_graph
    from depth_fusion_ros.multiview.views import prepare_views

    grays, _, poses = planes_views
    args = (grays[0], poses[0], grays[1:], poses[1:], CAMERA)
    eager = estimate_semidense(*args, config, neighbours=(1, 2, 3, 4))
    views = prepare_views(*args, 'cpu')
    recorded = semidense_graph.estimate(views, config, 2, (1, 2, 3, 4), graph=False)
    assert 0 < eager.candidates.sum() <= semidense_graph.candidate_capacity(config, CAMERA)
    assert np.array_equal(eager.candidates, recorded.candidates)
    assert np.array_equal(eager.valid, recorded.valid) and eager.valid.sum() > 0
    np.testing.assert_allclose(recorded.depth[eager.valid], eager.depth[eager.valid], rtol=1e-5)
    for name in ('score', 'depth_std', 'geometric_score', 'distinctiveness', 'sharpness', 'cost'):
        got, want = getattr(recorded, name)[eager.valid], getattr(eager, name)[eager.valid]
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6, err_msg=name)
    assert recorded.neighbours == eager.neighbours
