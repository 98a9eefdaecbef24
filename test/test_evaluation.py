"""The evaluation harness: registry, scoring, results.json schema, report and figures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.sequence import Frame, Sequence
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.harness import evaluate_sequence, results_document, write_outputs
from depth_fusion_ros.evaluation.registry import available_methods, get_method


def tiny_sequence(n: int = 6) -> Sequence:
    """A slanted wall seen by a sliding camera, with a hole in the ground truth."""
    cam = PinholeCamera(64, 48, 60.0, 60.0, 31.5, 23.5)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(n):
        depth = np.tile(np.linspace(1.0, 3.0, 64, dtype=np.float32), (48, 1))
        depth[:5, :5] = np.nan
        pose = np.eye(4)
        pose[0, 3] = 0.01 * i
        rgb = rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8)
        frames.append(Frame(i, 100.0 + i / 30, rgb, pose, depth))
    return Sequence('tiny', cam, frames, gt_camera=cam)


def test_unknown_method_lists_available():
    with pytest.raises(KeyError, match=r'available: .*constant_median'):
        get_method('no_such_method')
    assert {'ground_truth', 'constant_median'} <= set(available_methods())


def test_ground_truth_scores_zero_and_constant_median_does_not(tmp_path):
    seq = tiny_sequence()
    opts = EvalOptions(frames=None, width=64, height=48)
    result = evaluate_sequence(seq, ['ground_truth', 'constant_median'], opts, show_progress=False)
    doc = results_document([result], ['ground_truth', 'constant_median'], opts)
    methods = doc['sequences']['tiny']['methods']
    assert methods['ground_truth']['mae'] == 0 and methods['ground_truth']['si'] == pytest.approx(0)
    assert methods['constant_median']['mae'] > 0.3
    assert len(methods['constant_median']['per_frame_mae']) == len(seq)
    assert methods['ground_truth']['n_pixels'] == len(seq) * (64 * 48 - 25)

    write_outputs(doc, [result], tmp_path)
    loaded = json.loads((tmp_path / 'results.json').read_text())
    entry = loaded['sequences']['tiny']
    assert entry['frames'] == len(seq)
    for key in ('mae', 'rmse', 'si', 'abs_rel', 'delta1', 'n_pixels', 'per_frame_mae'):
        assert key in entry['methods']['constant_median']
    report = (tmp_path / 'report.md').read_text()
    assert '| constant_median |' in report
    assert (tmp_path / 'tiny_depths.png').stat().st_size > 0


def test_stride_and_reproducibility():
    seq = tiny_sequence(7)
    opts = EvalOptions(frames=None, stride=3, width=64, height=48)
    a = evaluate_sequence(seq, ['constant_median'], opts, show_progress=False)
    b = evaluate_sequence(seq, ['constant_median'], opts, show_progress=False)
    assert a.keyframes == [0, 3, 6]
    ja, jb = (r.records['constant_median'].to_json() for r in (a, b))
    ja.pop('seconds_per_frame'), jb.pop('seconds_per_frame')  # the only thing allowed to differ
    assert ja == jb
