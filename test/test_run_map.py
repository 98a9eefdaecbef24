"""``depth-fusion run --map / --save-map``: map_node in the graph, its mesh written at the end."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from depth_fusion_ros.nodes.graph.map_output import check_saved_map

pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')
torch = pytest.importorskip('torch')

from conftest import save_torchscript_depth_model  # noqa: E402
from run_bags import header_stamps, small_bag, write_params  # noqa: E402

POSE = '/depth_fusion/keyframe/pose'
FUSED = '/depth_fusion/fused/depth'
CONFIDENCE = '/depth_fusion/fused/confidence'
INFO = '/depth_fusion/fused/camera_info'
KEYFRAME_IMAGE = '/depth_fusion/keyframe/image'
POSING = (
    '/depth_fusion/posing/camera_from_pose_frame',
    '/depth_fusion/posing/pose_time',
    '/depth_fusion/posing/reposed_keyframes',
)


class _ToyDepth(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 + 0.5 * torch.sigmoid(x.mean(dim=1, keepdim=True))


def test_save_map_writes_the_mesh_of_every_fused_keyframe(synthetic_tum_dir, tmp_path):
    from depth_fusion_ros.mapping.ply import read_ply
    from depth_fusion_ros.nodes.graph import RunOptions, run_graph

    model = save_torchscript_depth_model(_ToyDepth(), tmp_path, 'toy')
    params = write_params(tmp_path / 'params.yaml', model)
    bag = small_bag(synthetic_tum_dir, tmp_path / 'bag')
    out = tmp_path / 'maps' / 'room.ply'
    result = run_graph(
        RunOptions(bag=bag, params_file=params, record=tmp_path / 'rec', save_map=out, flush_timeout=120.0)
    )
    assert result.complete and result.fused, result
    assert result.map_error is None and result.map_file == out
    mesh = read_ply(out)
    assert result.map_size == (len(mesh.vertices), len(mesh.triangles)) and len(mesh.vertices) > 0
    map_stats = result.node_stats['map_node']
    assert map_stats.published.get('integrated') == len(result.fused)  # every fused keyframe is in the map
    # the keyframe poses the map used are recorded with the fused depth, stamp for stamp
    assert header_stamps(tmp_path / 'rec', POSE) == header_stamps(tmp_path / 'rec', FUSED)
    # and the posing they were posed with, latched as published, so a replay latches it too
    from rosbags.rosbag2 import Reader

    from depth_fusion_ros.data.bag_qos import recorded_latched_depth

    with Reader(tmp_path / 'rec') as rec:
        latched = {c.topic: recorded_latched_depth(c) for c in rec.connections if '/posing/' in c.topic}
    assert set(latched) == set(POSING) and all(latched.values()), latched
    told = header_stamps(tmp_path / 'rec', POSING[0])
    assert told and min(told) <= min(header_stamps(tmp_path / 'rec', FUSED))  # said with the first frame
    # The recording maps again offline: replayed into a map_node of its own (the posings
    # latched as recorded), it gives the run's mesh.
    again = _map_from_recording(tmp_path / 'rec', tmp_path / 'again.ply', len(result.fused))
    assert again.vertices.shape == mesh.vertices.shape
    assert np.abs(np.sort(again.vertices, axis=0) - np.sort(mesh.vertices, axis=0)).max() < 1e-4


def _map_from_recording(rec, out, keyframes: int):
    """A map_node fed by ``bag_replayer`` from a ``--record`` recording; its saved mesh."""
    from map_inputs import call_save
    from rclpy.parameter import Parameter

    from depth_fusion_ros.mapping.ply import read_ply
    from depth_fusion_ros.nodes.bag_replayer import BagReplayer
    from depth_fusion_ros.nodes.map_node import MapNode
    from depth_fusion_ros.nodes.testing import RosHarness

    inputs = [FUSED, CONFIDENCE, INFO, POSE, KEYFRAME_IMAGE, *POSING]
    with RosHarness() as ros:
        lossless = {'queue_size': 16, 'queue_policy': 'block', 'qos_depth': 100}
        params = {**lossless, 'save_path': str(out), 'points_rate': 0.0}
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        node = ros.add(MapNode(context=ros.context, parameter_overrides=overrides))
        replayer = BagReplayer(
            context=ros.context,
            parameter_overrides=[
                Parameter('bag', value=str(rec)),
                Parameter('topics', value=inputs),
                Parameter('qos_depth', value=100),
                Parameter('wait_for_subscribers', value=1),
                Parameter('wait_topics', value=[FUSED]),
            ],
            autostart=False,
        )
        ros.add(replayer)
        replayer.start()
        assert replayer.finished.wait(60.0) and replayer.error is None
        assert ros.wait_for(lambda: node.integrated == keyframes and node.worker.idle(), 60.0), (
            node.stats.snapshot().summary()
        )
        posings = node.corrector.posings
        assert posings.transforms and posings.offsets  # heard from the replay, latched as recorded
        saved = call_save(ros)
        assert saved.success, saved.message
    return read_ply(out)


def test_no_map_written_is_an_error_not_a_success(tmp_path):
    stale = tmp_path / 'old.ply'
    stale.write_bytes(b'ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n')
    file, size, why = check_saved_map(stale, since_wall=stale.stat().st_mtime + 60.0)  # from an earlier run
    assert file is None and size is None and 'wrote no map' in why
    file, size, why = check_saved_map(tmp_path / 'missing.ply', since_wall=0.0)
    assert file is None and 'wrote no map' in why
    assert check_saved_map(stale, since_wall=0.0)[1] == (3, 0)


def _args(*argv: str) -> argparse.Namespace:
    from depth_fusion_ros.cli.main import build_parser

    return build_parser().parse_args(['run', '--bag', 'b', *argv])


def test_map_options_are_checked_before_anything_runs(tmp_path):
    from depth_fusion_ros.cli.run import options_from_args

    with pytest.raises(ValueError, match='map_node is not started; add --map'):
        options_from_args(_args('--set', 'map_node.map.voxel_size=0.02'))
    with pytest.raises(ValueError, match=r'written as \.ply'):
        options_from_args(_args('--save-map', str(tmp_path / 'm.obj')))
    opts = options_from_args(
        _args('--save-map', str(tmp_path / 'm.ply'), '--set', 'map_node.map.voxel_size=0.02')
    )
    assert opts.with_map and opts.save_map == tmp_path / 'm.ply'
    assert options_from_args(_args('--map')).with_map
    assert not options_from_args(_args()).with_map
