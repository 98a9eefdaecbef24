"""The calibration check commands on a robot's own recording: its topic names, its pose type
and the pose of a body rather than of the camera (``--image-topic``, ``--camera-info-topic``,
``--pose-topic``, ``--camera-from-pose-frame``), read as multi_view_node reads them."""

from __future__ import annotations

import pytest
from robot_bag import MOUNT, ROBOT, robot_bag

from depth_fusion_ros.cli.main import main
from depth_fusion_ros.data.synthetic import stress_config, write_synthetic_sequence

#: 320x240 over a 1 m sweep in 40 frames, as test_focal_check.
SIZE = {'width': 320, 'height': 240, 'frames': 40, 'seed': 5}
PAIRS = ['--pairs', '12']


def test_check_focal_reads_a_robots_topics_and_body_poses(tmp_path, capsys):
    """The wrong-focal stream recorded by a robot (its topic names, Odometry of its body) gives
    the check the verdict and the fit of the camera-posed recording once told its topics and
    the camera's mount; without the mount the poses are the body's, and the fit is another."""
    wrong = write_synthetic_sequence(tmp_path / 'wrong', stress_config('wrong_focal', **SIZE))
    assert main(['convert', str(wrong), str(tmp_path / 'bag'), '--no-depth']) == 0
    robot = robot_bag(tmp_path / 'bag', tmp_path / 'robot')
    capsys.readouterr()
    assert main(['check-focal', str(tmp_path / 'bag'), *PAIRS]) == 3
    reference = capsys.readouterr().out.strip().split(': ', 1)[1]
    assert 'camera_info says fx 288.8 px' in reference
    assert main(['check-focal', str(robot), *PAIRS, *ROBOT, '--camera-from-pose-frame', *MOUNT]) == 3
    assert capsys.readouterr().out.strip().split(': ', 1)[1] == reference
    main(['check-focal', str(robot), *PAIRS, *ROBOT])  # the body's poses as the camera's
    assert capsys.readouterr().out.strip().split(': ', 1)[1] != reference


def test_topics_for_a_tum_folder_and_a_bad_mount_are_one_line_errors(tmp_path, capsys):
    folder = write_synthetic_sequence(tmp_path / 'tum', stress_config('translation', **{**SIZE, 'frames': 4}))
    capsys.readouterr()
    assert main(['check-mount', str(folder), '--pose-topic', '/odom']) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and '--pose-topic: topics are for a rosbag2' in err, err
    bad = ['0', '0', '0', '0', '0', '0', '2']
    assert main(['check-sync', str(folder), '--camera-from-pose-frame', *bad]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and "'--camera-from-pose-frame'" in err and 'has norm 2' in err, err


@pytest.mark.parametrize('command', ['check-focal', 'check-sync', 'check-mount', 'evaluate', 'adapt'])
def test_every_check_command_takes_the_robot_options(command, capsys):
    """The check commands, ``evaluate`` and ``adapt`` read a robot's recording alike; only
    ``evaluate`` scores against depth, so only it takes a depth topic."""
    with pytest.raises(SystemExit):
        main([command, '--help'])
    out = capsys.readouterr().out
    for option in ('--image-topic', '--camera-info-topic', '--pose-topic', '--camera-from-pose-frame'):
        assert option in out
    assert ('--depth-topic' in out) == (command == 'evaluate')
