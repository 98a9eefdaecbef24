"""The graph runner's pieces that need no running graph: profile, params, commands, CLI errors."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip('rclpy', reason='rclpy (ros-jazzy-rclpy) is not installed')

from depth_fusion_ros.nodes import graph as launcher


def test_fastdds_profile_is_shipped_and_kept_when_user_set_one(tmp_path):
    path = launcher.fastdds_profile_path()
    text = path.read_text()
    assert '<type>SHM</type>' in text and '<segment_size>10485760</segment_size>' in text
    env: dict[str, str] = {}
    assert launcher.apply_fastdds_profile(env) == str(path)
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == env['FASTDDS_DEFAULT_PROFILES_FILE'] == str(path)
    mine = {'FASTRTPS_DEFAULT_PROFILES_FILE': str(tmp_path / 'mine.xml')}
    assert launcher.apply_fastdds_profile(mine) == str(tmp_path / 'mine.xml')


def test_fastdds_profile_parses_and_announces_fast(tmp_path):
    # Fast DDS ignores a profile it cannot parse (only a log line says so): the nodes would then
    # lose the 10 MB segment and the 0.5 s announcements (time to ready) without failing.
    import xml.etree.ElementTree as ET

    root = ET.parse(launcher.fastdds_profile_path()).getroot()
    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    period = root.find('.//p:discovery_config/p:leaseAnnouncement', ns)
    assert period is not None and float(period.find('p:nanosec', ns).text) == 5e8
    code = 'import rclpy; rclpy.init(); rclpy.create_node("profile_check").destroy_node(); rclpy.shutdown()'
    env = dict(os.environ, ROS_DOMAIN_ID='231', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    env.update({name: str(launcher.fastdds_profile_path()) for name in launcher.PROFILE_ENV})
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert 'XMLPARSER' not in out.stdout + out.stderr, out.stderr


def test_a_node_started_on_its_own_takes_the_package_profile_unless_one_is_set(tmp_path):
    from depth_fusion_ros.nodes.graph.dds import profile_for_console_node

    env: dict[str, str] = {}
    line = profile_for_console_node(env)
    assert env['FASTRTPS_DEFAULT_PROFILES_FILE'] == str(launcher.fastdds_profile_path())
    assert "the package's" in line and 'FASTDDS_DEFAULT_PROFILES_FILE' in line
    mine = {'FASTDDS_DEFAULT_PROFILES_FILE': str(tmp_path / 'mine.xml')}
    line = profile_for_console_node(mine)
    assert 'yours' in line and str(tmp_path / 'mine.xml') in line
    assert mine == {'FASTDDS_DEFAULT_PROFILES_FILE': str(tmp_path / 'mine.xml')}


def test_topic_names_match_the_nodes():
    from depth_fusion_ros.nodes import fusion_node, multi_view_node, single_view_node

    assert launcher.TOPIC_IMAGE == '/' + multi_view_node.TOPIC_IMAGE
    assert launcher.TOPIC_CAMERA_INFO == '/' + multi_view_node.TOPIC_CAMERA_INFO
    assert launcher.TOPIC_POSE == '/' + multi_view_node.TOPIC_POSE
    assert launcher.TOPIC_KEYFRAME_IMAGE == '/' + multi_view_node.TOPIC_KEYFRAME_IMAGE
    assert launcher.TOPIC_MV_DEPTH == '/' + multi_view_node.TOPIC_DEPTH
    assert launcher.TOPIC_SINGLE_DEPTH == '/' + single_view_node.TOPIC_DEPTH
    assert launcher.TOPIC_FUSED_DEPTH == '/' + fusion_node.TOPIC_FUSED_DEPTH
    assert launcher.TOPIC_FUSED_CONFIDENCE == '/' + fusion_node.TOPIC_FUSED_CONFIDENCE
    assert launcher.TOPIC_FUSED_CAMERA_INFO == '/' + fusion_node.TOPIC_FUSED_CAMERA_INFO
    from depth_fusion_ros.nodes import posing
    from depth_fusion_ros.nodes.graph import topics

    assert set(topics.POSING_TOPICS) == {
        '/' + t
        for t in (posing.TOPIC_POSING_TRANSFORM, posing.TOPIC_POSING_TIME, posing.TOPIC_REPOSED_KEYFRAMES)
    }
    for name, (_, module) in launcher.GRAPH_NODES.items():
        declared = importlib.import_module(module).NODE_NAME
        assert declared == name


def test_params_file_reading_and_overrides(tmp_path):
    params = tmp_path / 'p.yaml'
    params.write_text(
        '/**:\n  ros__parameters:\n    device: cuda\n'
        'fusion_node:\n  ros__parameters:\n    output_qos: sensor_data\n    fusion:\n      mode: exact\n'
        'bag_replayer:\n  ros__parameters:\n    topics: [/camera/pose]\n'
    )
    read = launcher.read_params_file(params)
    assert read['fusion_node'] == {'output_qos': 'sensor_data', 'fusion.mode': 'exact'}
    assert launcher.param_from_file(read, 'multi_view_node', 'device') == 'cuda'
    options = launcher.RunOptions(bag=Path('b'), params_file=params, rate=2.0, single_view_model='m.pt')
    assert launcher.recorder_qos(options) == 'sensor_data'
    over = launcher.node_overrides(options, ['/camera/pose', '/camera/depth/image'])
    assert over['bag_replayer']['rate'] == 2.0 and 'topics' not in over['bag_replayer']  # file decides
    assert over['single_view_node'] == {'model': 'm.pt'}
    plain = launcher.node_overrides(launcher.RunOptions(bag=Path('b')), ['/a', '/camera/depth/image'])
    assert plain['bag_replayer']['topics'] == ['/a'], 'ground truth is not played by default'
    assert 'rate' not in plain['bag_replayer']


def test_bad_params_files_raise_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match='params file'):
        launcher.read_params_file(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('fusion_node:\n  device: cpu\n')
    with pytest.raises(ValueError, match='ros__parameters'):
        launcher.read_params_file(bad)
    bad.write_text('a: [\n')
    with pytest.raises(ValueError, match='not valid YAML'):
        launcher.read_params_file(bad)


def test_ros_arg_values_and_node_commands():
    assert launcher.ros_arg_value(True) == 'true'
    assert launcher.ros_arg_value(0.5) == '0.5'
    assert launcher.ros_arg_value(['/a', '/b']) == '[/a, /b]'
    assert launcher.ros_arg_value('cuda') == 'cuda'
    assert launcher.ros_arg_value('123') == "'123'"
    cmd = launcher.node_command('bag_replayer', 'depth_fusion_ros.nodes.bag_replayer', ['-p', 'x:=1'])
    assert cmd[-3:] == ['--ros-args', '-p', 'x:=1']
    fallback = launcher.node_command('no_such_script_x', 'pkg.mod', [])
    assert fallback == [sys.executable, '-m', 'pkg.mod', '--ros-args']


def test_cli_reports_a_missing_bag_without_traceback(tmp_path):
    out = subprocess.run(
        [sys.executable, '-m', 'depth_fusion_ros.cli.main', 'run', '--bag', str(tmp_path / 'nope')],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 1
    assert f'bag {tmp_path / "nope"} does not exist' in out.stderr and 'Traceback' not in out.stderr


def test_cli_help_documents_the_options():
    out = subprocess.run(
        [sys.executable, '-m', 'depth_fusion_ros.cli.main', 'run', '--help'], capture_output=True, text=True
    )
    for flag in (
        '--bag',
        '--params',
        '--record',
        '--processes',
        '--rate',
        '--device',
        '--single-view',
        '--set',
    ):
        assert flag in out.stdout


def test_running_doc_lists_every_replayer_and_recorder_parameter():
    from depth_fusion_ros.nodes.bag_replayer import REPLAYER_PARAMS
    from depth_fusion_ros.nodes.recorder import RECORDER_PARAMS

    doc = (Path(__file__).resolve().parents[1] / 'docs' / 'running.md').read_text()
    for spec in (*REPLAYER_PARAMS, *RECORDER_PARAMS):
        assert f'| `{spec.name}` |' in doc, f'docs/running.md does not describe {spec.name}'


def test_segments_of_a_killed_node_are_found_and_removed():
    """What the no-leftover checks rely on: SIGKILL leaves a participant segment whose owner is
    gone, though other participants may still map it.

    Judged on the doomed node's own segments (among those it maps, the ones created since the
    test began whose locks are free once it is dead; it maps an older orphan it found too): tests
    on the other pytest workers kill nodes too, and their orphans appear in the same /dev/shm
    meanwhile (a full run once counted 4)."""
    import os
    import signal
    import time

    from depth_fusion_ros.nodes.graph.dds import owner_alive, participant_segments_of, shm_segments

    since = time.time()
    code = (
        'import rclpy, time; rclpy.init(); n = rclpy.create_node("doomed"); '
        'print("up", flush=True); time.sleep(60)'
    )
    env = os.environ.copy()
    launcher.apply_fastdds_profile(env)
    proc = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == 'up'
        time.sleep(0.5)
        mapped = participant_segments_of(proc.pid)
        assert mapped and all(owner_alive(s) for s in mapped), mapped
        assert not mapped & set(launcher.orphan_segments(since)), 'a live node segment is not an orphan'
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    created = shm_segments()
    own = {s for s in mapped if owner_alive(s) is False and created.get(s, 0.0) >= since}
    assert own, f'the killed node left no segment of its own (or it was not recognised): {mapped}'
    orphans = launcher.orphan_segments(since)
    assert own <= set(orphans), orphans
    launcher.remove_segments([n for n in orphans if n.removesuffix('_el') in own])
    assert not own & {n.removesuffix('_el') for n in launcher.orphan_segments(since)}
    assert not [s for s in own if (Path('/dev/shm') / s).exists()]
