"""The TSDF map saved to disk and loaded back (map_node's map_file): core, no ROS."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.mapping.config import MapConfig, min_weight_for
from depth_fusion_ros.mapping.keyframe_store import KeyframeStore, rebuild
from depth_fusion_ros.mapping.map_file import (
    file_min_weight,
    file_powers,
    load_map,
    load_tsdf,
    read_state,
    save_tsdf,
)
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF
from depth_fusion_ros.pose_corrections import CorrectionLimits, Posing


@pytest.fixture(scope='module')
def saved_map(tmp_path_factory):
    seq = render_sequence(SynthConfig(width=96, height=72, frames=4, seed=4))
    tsdf = TorchTSDF(MapConfig(voxel_size=0.05, engine='torch'))
    for i, frame in enumerate(seq.frames):
        tsdf.integrate(seq.gt_depth_working(i), frame.pose, seq.camera, rgb=frame.rgb)
    path = tmp_path_factory.mktemp('map') / 'room.tsdf'
    assert save_tsdf(tsdf, path, 'world') == tsdf.n_blocks > 10
    return tsdf, path, seq


def test_a_saved_map_loads_back_the_same_and_takes_more_keyframes(saved_map):
    tsdf, path, seq = saved_map
    loaded = TorchTSDF(MapConfig(voxel_size=0.05, engine='torch'))
    assert load_tsdf(loaded, path) == 'world'
    assert loaded.n_blocks == tsdf.n_blocks
    a, b = tsdf.mesh(), loaded.mesh()
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    loaded.integrate(seq.gt_depth_working(0), seq.frames[0].pose, seq.camera)  # integration goes on
    assert loaded.integrated == 1 and loaded.n_blocks == tsdf.n_blocks


def test_a_map_file_that_does_not_fit_is_a_one_line_error(saved_map, tmp_path):
    _, path, _ = saved_map
    with pytest.raises(ValueError, match=r'5 cm voxels .* configured for 4 cm'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.04, engine='torch')), path)
    with pytest.raises(ValueError, match=r'more than map\.max_blocks=3 with map\.archive off'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch', max_blocks=3, archive=False)), path)
    junk = tmp_path / 'junk.tsdf'
    junk.write_bytes(b'not a map')
    with pytest.raises(ValueError, match='not readable as a map'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch')), junk)
    other = tmp_path / 'other.tsdf'
    torch.save({'weights': torch.zeros(3)}, other)
    with pytest.raises(ValueError, match='not a depth_fusion_ros TSDF map'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch')), other)


def test_the_kept_keyframes_travel_with_the_map_and_a_rebuild_after_a_restart_moves_them(tmp_path):
    """A map file written with its keyframe store loads them back (poses, images, segments apart
    from the new stream), so the map can still be rebuilt at corrected poses; a file without
    them loads as a fixed base, as before."""
    seq = render_sequence(SynthConfig(width=96, height=72, frames=4, seed=4))
    config = MapConfig(voxel_size=0.05, engine='torch')
    tsdf, store = TorchTSDF(config), KeyframeStore(max_bytes=2**20)
    for i, frame in enumerate(seq.frames):
        depth = seq.gt_depth_working(i)
        tsdf.integrate(depth, frame.pose, seq.camera, rgb=frame.rgb)
        confidence = np.full(depth.shape, 0.5, np.float32)
        # The last two posed with a mount turn and a pose time offset (nodes/posing.py), the first as told.
        posing = Posing(np.diag([1.0, -1.0, -1.0, 1.0]), 0.025) if i >= 2 else None
        store.add(float(i), depth, frame.pose, seq.camera, confidence, frame.rgb, posing=posing)
    path = tmp_path / 'with_keyframes.tsdf'
    save_tsdf(tsdf, path, 'world', store=store)
    restored = KeyframeStore(max_bytes=2**20)
    loaded = load_map(TorchTSDF(config), path, restored)
    assert loaded.world_frame == 'world' and loaded.keyframes == 4 and loaded.base is None
    for a, b in zip(store.entries, restored.entries, strict=True):
        np.testing.assert_array_equal(a.T_wc, b.T_wc)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        assert (a.posing is None and b.posing is None) or (
            a.posing is not None
            and b.posing is not None
            and a.posing.offset == b.posing.offset
            and np.array_equal(a.posing.T_pose_cam, b.posing.T_pose_cam)
        )
        assert a.confidence is not None and np.array_equal(a.confidence, b.confidence)
        assert a.camera == b.camera and a.stamp == b.stamp
    assert {e.segment for e in restored.entries} == {1} and restored.segment == 2  # what follows: a new world
    # A correction of 0.3 m along x moves the rebuilt map by as much. The path is the pose
    # source's: each keyframe's pose at its stamp plus its offset, in the pose's frame.
    shift = np.eye(4)
    shift[0, 3] = 0.3
    told = Posing(np.eye(4))
    restored.correct(
        np.array([e.stamp + (e.posing or told).offset for e in restored.entries]),
        np.stack([shift @ e.T_wc @ np.linalg.inv((e.posing or told).T_pose_cam) for e in restored.entries]),
        CorrectionLimits(max_gap=10.0),
        told,
    )
    rebuilt, at_old = TorchTSDF(config), TorchTSDF(config)
    rebuild(rebuilt, restored.entries)
    rebuild(at_old, store.entries)
    old_surface = cKDTree(at_old.mesh().vertices)
    moved = rebuilt.mesh().vertices
    back, unmoved = old_surface.query(moved - [0.3, 0.0, 0.0])[0], old_surface.query(moved)[0]
    assert np.percentile(back, 90) < 0.02 < 0.1 < np.percentile(unmoved, 90)  # on it, once moved back
    # With a fixed base beside the keyframes, the base comes back as it was.
    base = tsdf.blocks().clone()
    save_tsdf(tsdf, path, 'world', store=store, base=base)
    loaded = load_map(TorchTSDF(config), path, KeyframeStore(max_bytes=2**20))
    torch.testing.assert_close(loaded.base.tsdf, base.tsdf, rtol=0, atol=0)
    # Without keyframes (an older file, or no store): everything is the fixed base.
    save_tsdf(tsdf, path, 'world')
    loaded = load_map(TorchTSDF(config), path, KeyframeStore(max_bytes=2**20))
    assert loaded.keyframes == 0 and loaded.base.coords.shape[0] == tsdf.n_blocks


def test_depth_fusion_mesh_writes_the_mesh_of_a_map_file(saved_map, tmp_path, capsys):
    """`depth-fusion mesh`: the saved map's surface as ~/save_map would write it; an unreadable
    file is a one-line error (2) and a map without surface writes nothing (1)."""
    from depth_fusion_ros.cli.main import main
    from depth_fusion_ros.mapping import read_ply

    tsdf, path, _ = saved_map
    out = tmp_path / 'offline.ply'
    assert main(['mesh', str(path), '--out', str(out), '--max-blocks', '7']) == 0
    expected, got = tsdf.mesh(), read_ply(out)
    assert len(got.vertices) == len(expected.vertices) and len(got.triangles) == len(expected.triangles)
    np.testing.assert_array_equal(np.sort(got.vertices, axis=0), np.sort(expected.vertices, axis=0))
    assert f'{len(expected.vertices)} vertices' in capsys.readouterr().out
    junk = tmp_path / 'junk.tsdf'
    junk.write_bytes(b'not a map')
    assert main(['mesh', str(junk), '--out', str(out)]) == 2
    assert 'not readable as a map' in capsys.readouterr().err
    assert main(['mesh', str(path), '--out', str(tmp_path / 'none.ply'), '--min-weight', '1e9']) == 1
    assert 'has no surface' in capsys.readouterr().err and not (tmp_path / 'none.ply').exists()
    assert main(['mesh', str(path), '--out', str(out)]) == 2  # the first .ply is kept
    assert 'already exists (pass --overwrite' in capsys.readouterr().err
    assert len(read_ply(out).vertices) == len(expected.vertices)
    assert main(['mesh', str(path), '--out', str(out), '--overwrite']) == 0


def test_a_map_saved_with_other_weights_says_so_and_meshes_at_its_own_threshold(tmp_path, caplog):
    """The file records what its weights are (the confidence to ``map.confidence_power`` over the
    depth to ``map.depth_power``); a node that weighs new keyframes otherwise says so in one line,
    and ``depth-fusion mesh`` extracts an older file at the threshold of the same single
    observation at 2.5 m."""
    from depth_fusion_ros.cli.main import main

    depth = np.full((36, 48), 1.5, np.float32)
    confidence = np.full(depth.shape, 0.04, np.float32)  # one look: 0.04
    camera = PinholeCamera(48, 36, 40.0, 40.0, 23.5, 17.5)
    old = TorchTSDF(MapConfig(voxel_size=0.05, engine='torch', confidence_power=1.0, depth_power=0.0))
    old.integrate(depth, np.eye(4), camera, confidence=confidence)
    path = tmp_path / 'old.tsdf'
    save_tsdf(old, path, 'world')
    assert file_powers(read_state(path)) == (1.0, 0.0)
    # The default 0.00032 of squared confidence over squared depth is 0.002 of squared confidence
    # at 2.5 m, 0.0447 of plain confidence: the one look at 0.04 is under both.
    assert file_min_weight(read_state(path), MapConfig()) == pytest.approx(0.002**0.5)  # mesh, load_map
    assert min_weight_for(MapConfig(), 2.0, 0.0) == pytest.approx(0.002)
    assert min_weight_for(MapConfig(), 2.0, 2.0) == MapConfig().min_weight
    assert main(['mesh', str(path), '--out', str(tmp_path / 'a.ply')]) == 1
    assert main(['mesh', str(path), '--out', str(tmp_path / 'b.ply'), '--min-weight', '0.03']) == 0
    with caplog.at_level('WARNING'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch')), path)
    said = 'the confidence to the power 1 over the depth to 0, new keyframes weigh them 2 and 2'
    assert said in caplog.text
