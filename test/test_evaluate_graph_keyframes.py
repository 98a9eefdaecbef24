"""``evaluate`` of a recorded graph: the keyframes its methods and the offline ones are scored
on. With a stride of 1 every frame was a keyframe and ``graph_fused`` had output for only the
graph's (every fifth): the table set its MAE beside the offline methods' over other frames
and said nothing of it. Now the report says so, and ``--recorded-keyframes`` scores every
method on the graph's keyframes, as the demo does.

The "recording" here is a converted bag whose ground-truth depth topic stands in for the fused
depth (``--set recorded.graph_fused=TOPIC``): it holds the first 6 of the sequence's frames.
"""

from __future__ import annotations

import json

import pytest
from run_bags import small_bag

from depth_fusion_ros.cli.main import main

STAND_IN = ['--set', 'recorded.graph_fused=/camera/depth/image']


@pytest.fixture(scope='module')
def recording(synthetic_tum_dir, tmp_path_factory):
    return small_bag(synthetic_tum_dir, tmp_path_factory.mktemp('rec') / 'rec', frames=6)


def _evaluate(tum_dir, recording, out, *extra: str) -> dict:
    argv = ['evaluate', str(tum_dir), '--frames', '12', '--methods', 'graph_fused,single_view']
    argv += ['--single-view', 'simulated', '--set', f'recorded.bag={recording}', *STAND_IN, '--out', str(out)]
    assert main([*argv, '--no-figures', *extra]) == 0
    return json.loads((out / 'results.json').read_text())


def test_a_graph_method_with_output_for_some_keyframes_is_said_in_the_report(
    synthetic_tum_dir, recording, tmp_path
):
    doc = _evaluate(synthetic_tum_dir, recording, tmp_path / 'all')
    (seq,) = doc['sequences'].values()
    assert seq['keyframes'] == list(range(12))
    assert seq['methods']['graph_fused']['published'] == pytest.approx(0.5)
    report = (tmp_path / 'all' / 'report.md').read_text()
    assert (
        '`graph_fused`: the graph published 6 of these 12 keyframes; its figures are over those alone'
        in report
    )
    assert 'keyframe stride 1' in report


def test_recorded_keyframes_score_every_method_on_the_graphs_keyframes(
    synthetic_tum_dir, recording, tmp_path
):
    doc = _evaluate(synthetic_tum_dir, recording, tmp_path / 'graph', '--recorded-keyframes')
    (seq,) = doc['sequences'].values()
    assert seq['keyframes'] == list(range(6))
    assert seq['methods']['graph_fused']['published'] == 1.0
    assert seq['methods']['graph_fused']['mae'] < 1e-3  # the stand-in is the ground truth
    report = (tmp_path / 'graph' / 'report.md').read_text()
    assert 'keyframes: those the recorded node graph fused' in report and 'the graph published' not in report


@pytest.mark.parametrize(
    ('extra', 'said'),
    [
        (['--methods', 'graph_fused'], 'graph_fused needs the recorded bag: --set recorded.bag=PATH'),
        (['--recorded-keyframes'], '--recorded-keyframes needs the recorded bag: --set recorded.bag=PATH'),
        (
            ['--set', 'recorded.bag=/no/such/bag', '--methods', 'graph_fused'],
            'recorded.bag /no/such/bag: no such bag',
        ),
        (
            ['--set', 'recorded.bag=REC', '--recorded-keyframes', '--stride', '2'],
            '--stride and --recorded-keyframes both choose the keyframes: give one',
        ),
    ],
)
def test_the_recording_is_checked_before_any_data_loads(
    extra, said, synthetic_tum_dir, recording, capsys, caplog
):
    extra = [f'recorded.bag={recording}' if a == 'recorded.bag=REC' else a for a in extra]
    assert main(['evaluate', str(synthetic_tum_dir), '--single-view', 'simulated', *extra]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == f'depth-fusion evaluate: error: {said}'
    assert 'frames loaded' not in caplog.text
