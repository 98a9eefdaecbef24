"""evaluate's map methods: scored once per sequence against the ground-truth-depth map."""

from __future__ import annotations

import json

import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.evaluation.context import EvalOptions
from depth_fusion_ros.evaluation.harness import evaluate_sequence, results_document, write_outputs
from depth_fusion_ros.mapping.scoring import score_map
from depth_fusion_ros.mapping.surface import SurfaceMesh

pytestmark = pytest.mark.usefixtures('one_torch_thread')

MAP_KEYS = ('map_accuracy_median_m', 'map_accuracy_mean_m', 'map_completeness_5cm', 'map_completeness_10cm')


def test_map_methods_report_accuracy_completeness_and_a_picture(tmp_path):
    seq = render_sequence(SynthConfig(width=160, height=120, frames=12, seed=2))
    methods = ['single_view_simulated', 'map', 'map_single_view', 'map_multi_view']
    options = EvalOptions(
        frames=12, stride=4, single_view='simulated', params={'fusion': {'compile_kernel': False}}
    )
    result = evaluate_sequence(seq, methods, options, show_progress=False)
    doc = results_document([result], methods, options)
    write_outputs(doc, [result], tmp_path)
    scores = json.loads((tmp_path / 'results.json').read_text())['sequences'][seq.name]['methods']
    for name in ('map', 'map_single_view', 'map_multi_view'):
        assert all(key in scores[name] for key in MAP_KEYS), name
        assert 'mae' not in scores[name]  # the per-keyframe depth of a map method is not scored
    assert scores['map_single_view']['map_points'] > 100
    assert scores['map']['map_lost_blocks'] == 0  # nothing evicted and lost: the scored map is whole
    assert 0.0 <= scores['map']['map_completeness_5cm'] <= scores['map']['map_completeness_10cm'] <= 1.0
    assert 'mae' in scores['single_view_simulated']  # ordinary methods are scored as before
    assert (tmp_path / f'{seq.name}_map.png').is_file()
    assert f'{seq.name}_map.png' in (tmp_path / 'report.md').read_text()
    # What the demo does with it: the fused map's mesh as map.ply.
    from depth_fusion_ros.demo import _write_map
    from depth_fusion_ros.mapping import read_ply

    mesh = read_ply(_write_map(result, tmp_path))
    assert len(mesh.vertices) == scores['map']['map_points']


def test_score_map_against_a_known_shift():
    """A plane scored against itself shifted by 3 cm: accuracy 3 cm, complete at 5 cm, not at 2 cm."""
    u, v = np.meshgrid(np.arange(0, 1.0, 0.04), np.arange(0, 1.0, 0.04))
    n = u.shape[0]
    vertices = np.stack((u.ravel(), v.ravel(), np.zeros(u.size)), axis=1).astype(np.float32)
    idx = np.arange(n * n).reshape(n, n)
    quads = np.stack((idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]), axis=-1).reshape(-1, 4)
    triangles = np.concatenate((quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]))
    colours = np.zeros_like(vertices, dtype=np.uint8)
    reference = SurfaceMesh(vertices, triangles, colours)
    shifted = SurfaceMesh(vertices + np.float32([0, 0, 0.03]), triangles, colours)
    scores = score_map(shifted, reference)
    assert scores['map_accuracy_median_m'] == pytest.approx(0.03, abs=1e-4)
    assert scores['map_completeness_5cm'] == 1.0 and scores['map_completeness_10cm'] == 1.0
    assert score_map(reference, reference)['map_accuracy_mean_m'] == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError, match='reference map is empty'):
        score_map(reference, SurfaceMesh(vertices[:0], triangles[:0], colours[:0]))
