"""``evaluate`` and ``adapt`` on a robot's own rosbag2: its topic names, its pose type, the pose of
a body rather than of the camera, and its depth as a RealSense publishes it (``--image-topic``,
``--camera-info-topic``, ``--pose-topic``, ``--depth-topic``, ``--camera-from-pose-frame``).
The scores must be those of the same recording in the layout ``convert`` writes."""

from __future__ import annotations

import json

import pytest
from robot_bag import DEPTH_TOPIC, MOUNT, ROBOT, robot_bag

from depth_fusion_ros.cli.main import main
from depth_fusion_ros.data.synthetic import stress_config, write_synthetic_sequence

#: A small sideways sweep: 12 frames at 160x120, every third a keyframe.
SIZE = {'width': 160, 'height': 120, 'frames': 12, 'seed': 5}
EVALUATE = [
    '--width',
    '160',
    '--height',
    '120',
    '--frames',
    '12',
    '--stride',
    '3',
    '--single-view',
    'simulated',
    '--methods',
    'single_view,multi_view',
    '--no-figures',
]


def _scores(out) -> dict[str, dict[str, float]]:
    """``{method: metrics}`` of the one sequence of ``out/results.json``."""
    (sequence,) = json.loads((out / 'results.json').read_text())['sequences'].values()
    assert sequence['keyframes'] == [0, 3, 6, 9], sequence
    return sequence['methods']


@pytest.fixture(scope='module')
def recordings(tmp_path_factory):
    """The sweep as ``convert`` writes it, and as a robot records it (with 16UC1 depth)."""
    root = tmp_path_factory.mktemp('recordings')
    folder = write_synthetic_sequence(root / 'tum', stress_config('translation', **SIZE))
    assert main(['convert', str(folder), str(root / 'bag'), '--no-progress']) == 0
    return root / 'bag', robot_bag(root / 'bag', root / 'robot', depth=True)


def test_evaluate_scores_a_robots_bag_as_the_converted_one(recordings, tmp_path):
    """Told its topics and the camera's mount, the robot's bag scores as the converted bag: the
    same keyframes and depth, up to the ground truth's millimetres (16UC1). Without the mount
    the body's poses are taken for the camera's, and the multi-view depth is another."""
    bag, robot = recordings
    assert main(['evaluate', str(bag), *EVALUATE, '--out', str(tmp_path / 'bag')]) == 0
    reference = _scores(tmp_path / 'bag')
    told = [*ROBOT, '--depth-topic', DEPTH_TOPIC]
    args = ['evaluate', str(robot), *EVALUATE, *told, '--camera-from-pose-frame', *MOUNT]
    assert main([*args, '--out', str(tmp_path / 'robot')]) == 0
    scores = _scores(tmp_path / 'robot')
    for method in ('single_view', 'multi_view'):
        assert scores[method]['mae'] == pytest.approx(reference[method]['mae'], abs=1e-3), method
        assert scores[method]['n_pixels'] == pytest.approx(reference[method]['n_pixels'], rel=0.01), method
    assert main(['evaluate', str(robot), *EVALUATE, *told, '--out', str(tmp_path / 'body')]) == 0
    body = _scores(tmp_path / 'body')
    assert body['multi_view']['mae'] != pytest.approx(reference['multi_view']['mae'], abs=1e-3)


def test_a_robots_bag_without_its_topics_is_a_one_line_error(recordings, tmp_path, capsys):
    """Read with the converter's topic names, the robot's bag names the topic it lacks and the
    topics it has; topic options with no rosbag2 among the sequences fail before any loading."""
    _, robot = recordings
    capsys.readouterr()
    assert main(['evaluate', str(robot), *EVALUATE, '--out', str(tmp_path / 'a')]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and '/cam/image_raw' in err, err
    folder = tmp_path / 'not_read'
    folder.mkdir()
    assert main(['evaluate', str(folder), '--depth-topic', DEPTH_TOPIC, '--out', str(tmp_path / 'b')]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and '--depth-topic: topics are for a rosbag2' in err, err


def test_adapt_takes_a_robots_bag_without_depth(recordings, tmp_path, capsys):
    """``adapt`` never reads depth, so a robot's bag without a depth topic is enough; told its
    topics and mount, it trains (one step a keyframe, to be quick) and writes a checkpoint."""
    bag, _ = recordings
    robot = robot_bag(bag, tmp_path / 'no_depth')
    out = tmp_path / 'adapted.pt'
    args = ['adapt', str(robot), '--out', str(out), '--width', '160', '--height', '120', '--frames', '6']
    quick = ['adaptation.min_points=20', 'adaptation.steps_per_keyframe=1', 'adaptation.replay_per_step=0']
    # Six frames at 160x120: the filter's points do not reach the first update's
    # half (adaptation.start_coverage, tested in test_adaptation.py); exit 1 "no update was kept".
    quick.append('adaptation.start_coverage=0.25')
    sets = [item for value in quick for item in ('--set', value)]
    assert main([*args, *ROBOT, '--camera-from-pose-frame', *MOUNT, *sets]) == 0
    assert out.is_file()
    assert 'wrote' in capsys.readouterr().out


def test_depth_in_another_frame_than_the_colour_is_said(recordings, tmp_path, caplog):
    """Depth whose frame_id is not the colour's (a RealSense's unaligned depth) is read as
    registered all the same, and a warning names both frames: it may be a registered depth
    with its sensor's name (TUM's), or not registered, and then every score is wrong."""
    from depth_fusion_ros.data.recording import load_recording

    bag, _ = recordings
    robot = robot_bag(bag, tmp_path / 'unaligned', depth=True, depth_frame='cam_depth_optical_frame')
    topics = {'image_topic': '/cam/image_raw', 'camera_info_topic': '/cam/camera_info', 'pose_topic': '/odom'}
    with caplog.at_level('WARNING', logger='depth_fusion_ros.data.rosbag_read'):
        sequence = load_recording(robot, 160, 120, 12, topics={**topics, 'depth_topic': DEPTH_TOPIC})
    assert len(sequence) == 12
    said = [r.getMessage() for r in caplog.records if 'registered to the colour camera' in r.getMessage()]
    assert len(said) == 1 and "'cam_depth_optical_frame'" in said[0], caplog.text
