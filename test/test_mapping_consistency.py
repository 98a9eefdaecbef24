"""The map's multi-keyframe consistency test: wrong depth stays out, the map lags and flushes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from map_geometry import room_surface_distance

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.synthetic import SynthConfig, build_world, render_sequence
from depth_fusion_ros.mapping import MapConfig, make_map
from depth_fusion_ros.mapping.consistency import agreeing_views

pytestmark = pytest.mark.usefixtures('one_torch_thread')

CAMERA = PinholeCamera(160, 120, 131.25, 131.25, 79.5, 59.5)


def consistent_views(depth, T_wc, others, camera, tolerance) -> np.ndarray:
    """:func:`agreeing_views` on numpy images, on the CPU."""
    views = [(torch.as_tensor(o), T) for o, T in others]
    return agreeing_views(torch.as_tensor(depth), T_wc, views, camera, tolerance).numpy()


def _pose(x: float) -> np.ndarray:
    """Camera ``x`` m to the right of the origin, looking down +z."""
    T = np.eye(4)
    T[0, 3] = x
    return T


def _wall(distance: float = 2.0) -> np.ndarray:
    return np.full((CAMERA.height, CAMERA.width), distance, np.float32)


def test_a_wrong_patch_finds_no_agreeing_keyframe():
    """A wall seen from three positions; one keyframe has a patch 30 % too far."""
    bad = _wall()
    bad[40:80, 60:100] *= 1.3
    others = [(_wall(), _pose(-0.1)), (_wall(), _pose(0.1))]
    count = consistent_views(bad, _pose(0.0), others, CAMERA, tolerance=0.05)
    assert (count[40:80, 60:100] == 0).all()
    good = np.ones_like(count, bool)
    good[40:80, 60:100] = False
    # The rest agrees with both, except the strips the other cameras do not see.
    assert (count[good] >= 1).mean() > 0.99 and (count[good] == 2).mean() > 0.8
    # Missing depth and points outside the other images never count as agreement.
    bad[0, 0] = np.nan
    count = consistent_views(bad, _pose(0.0), [(_wall(), _pose(5.0))], CAMERA, tolerance=0.05)
    assert count.max() == 0


def test_the_map_lags_the_span_and_flushes_the_rest():
    config = MapConfig(engine='torch', consistency_span=2)
    tsdf, _ = make_map(config)
    for i in range(3):
        tsdf.integrate(_wall(), _pose(0.02 * i), CAMERA)
        assert tsdf.engine.integrated == max(0, i - 1) and tsdf.pending == min(i + 1, 2)
    assert tsdf.flush() > 0
    assert tsdf.engine.integrated == 3 and tsdf.pending == 0 and tsdf.unchecked == 0
    assert not tsdf.mesh().is_empty


def test_span_zero_integrates_every_pixel_at_once_and_a_lone_keyframe_is_unchecked():
    plain, _ = make_map(MapConfig(engine='torch', consistency_span=0))
    plain.integrate(_wall(), _pose(0.0), CAMERA)
    assert plain.engine.integrated == 1 and plain.pending == 0
    lone, _ = make_map(MapConfig(engine='torch'))
    lone.integrate(_wall(), _pose(0.0), CAMERA)
    assert lone.engine.integrated == 0
    lone.flush()
    assert lone.engine.integrated == 1 and lone.unchecked == 1
    assert np.abs(lone.mesh().vertices[:, 2] - 2.0).max() < 0.01


def test_bad_consistency_settings_are_refused():
    for field, value in (('consistency_span', -1), ('consistency_tolerance', 0.0), ('consistency_views', 5)):
        with pytest.raises(ValueError, match=f'map.{field}'):
            MapConfig(**{field: value}).validate()


def test_a_corrupted_keyframe_leaves_no_surface_in_the_room():
    """The synthetic room from ground-truth depth, one keyframe's depth scaled by 1.25: with the
    test the map stays on the room's geometry; without it the wrong keyframe leaves a surface."""
    cfg = SynthConfig(width=160, height=120, frames=16, seed=5)
    scene, seq = build_world(cfg)[0], render_sequence(cfg)
    distances = {}
    for span in (0, 2):
        tsdf, _ = make_map(MapConfig(engine='torch', voxel_size=0.04, consistency_span=span))
        for i in range(0, len(seq), 2):
            depth = seq.gt_depth_working(i) * (1.25 if i == 8 else 1.0)
            tsdf.integrate(depth, seq.frames[i].pose, seq.camera)
        tsdf.flush()
        distances[span] = room_surface_distance(scene, tsdf.mesh().vertices.astype(np.float64))
    assert len(distances[2]) > 2000
    assert np.percentile(distances[2], 99) < 0.05
    assert np.percentile(distances[0], 99) > 2 * np.percentile(distances[2], 99)
