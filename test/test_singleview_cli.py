"""``depth-fusion train`` end to end, and the single_view evaluation methods."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_singleview_toy import toy_sequence

from depth_fusion_ros.cli.main import main
from depth_fusion_ros.evaluation.context import EvalOptions, KeyframeContext
from depth_fusion_ros.evaluation.harness import evaluate_sequence
from depth_fusion_ros.evaluation.methods.single_view import single_view_prediction
from depth_fusion_ros.evaluation.registry import get_method
from depth_fusion_ros.metrics import frame_metrics
from depth_fusion_ros.singleview.architectures import build_model
from depth_fusion_ros.singleview.checkpoint import load_checkpoint, save_checkpoint
from depth_fusion_ros.singleview.metadata import ModelMetadata, write_metadata_yaml
from depth_fusion_ros.singleview.predictor import load_predictor

pytestmark = pytest.mark.usefixtures('one_torch_thread')

TINY_ARGS = [
    '--arch-config', 'input_width=64', '--arch-config', 'input_height=48',
    '--arch-config', 'encoder_widths=[8, 8, 16, 16, 16]', '--arch-config', 'encoder_blocks=[0, 0, 0, 0, 0]',
    '--arch-config', 'decoder_widths=[16, 16, 8, 8]',
]  # fmt: skip
TINY = {
    'input_width': 64,
    'input_height': 48,
    'encoder_widths': [8, 8, 16, 16, 16],
    'encoder_blocks': [0, 0, 0, 0, 0],
    'decoder_widths': [16, 16, 8, 8],
}


def test_train_cli_trains_ships_and_resumes(synthetic_tum_dir, tmp_path, capsys):
    out, ship = tmp_path / 'run', tmp_path / 'shipped.pt'
    common = [str(synthetic_tum_dir), '--out', str(out), *TINY_ARGS, '--batch-size', '4', '--val-every', '2',
              '--threads', '1', '--no-progress', '--every', '2']  # fmt: skip
    assert main(['train', *common, '--steps', '4', '--ship', str(ship)]) == 0
    printed = capsys.readouterr().out
    assert 'step      4' in printed and 'shipped' in printed
    shipped = load_checkpoint(ship)
    info = shipped.metadata.info
    assert shipped.training_state is None and shipped.model.head.weight.dtype == torch.float32
    assert info['training_sources'][0].startswith('Synthetic room')
    assert 'depth-fusion' in info['command'] and info['training_samples'] > 0
    assert ship.with_suffix('.yaml').is_file()
    depth = load_predictor(ship).predict(np.zeros((240, 320, 3), np.uint8))
    assert depth.shape == (240, 320) and np.isfinite(depth).all()
    assert main(['train', *common, '--steps', '6', '--resume']) == 0
    assert load_checkpoint(out / 'last.pt').training_state['step'] == 6
    # user errors: one line, exit code 1
    assert main(['train', str(tmp_path / 'missing'), '--out', str(tmp_path / 'x')]) == 1
    assert 'not found' in capsys.readouterr().err
    assert main(['train', *common, '--steps', '6']) == 1  # exists without --resume


def _ctx(seq, index: int, shared: dict, **options) -> KeyframeContext:
    return KeyframeContext(seq, index, EvalOptions(width=64, height=48, **options), shared)


def test_simulated_methods_are_reproducible_and_cnn_like():
    seq = toy_sequence(3, 64, 48, seed=2)
    sim = get_method('single_view_simulated').fn(_ctx(seq, 1, {}, seed=4)).depth
    again = get_method('single_view').fn(_ctx(seq, 1, {}, seed=4, single_view='simulated')).depth
    other = get_method('single_view_simulated').fn(_ctx(seq, 1, {}, seed=5)).depth
    assert np.array_equal(sim, again) and not np.array_equal(sim, other)
    assert sim.shape == (48, 64) and np.isfinite(sim).all()
    assert 0.03 < frame_metrics(sim, seq.frames[1].depth)['abs_rel'] < 0.5
    tuned = _ctx(
        seq,
        1,
        {},
        seed=4,
        params={
            'simulated': {
                'segment_scale_sigma': 0.0,
                'global_scale_sigma': 0.0,
                'segment_offset_sigma': 0.0,
                'deformation_sigma': 0.0,
            }
        },
    )
    assert (
        frame_metrics(get_method('single_view_simulated').fn(tuned).depth, seq.frames[1].depth)['abs_rel']
        < 0.05
    )


def test_network_method_memoises_and_scores_metric_output(tmp_path):
    path = save_checkpoint(
        tmp_path / 'tiny.pt', build_model('compact', TINY), ModelMetadata(input_width=64, input_height=48)
    )
    seq = toy_sequence(2, 64, 48)
    shared: dict = {}
    ctx = _ctx(seq, 0, shared, single_view=str(path))
    first = single_view_prediction(ctx)
    assert single_view_prediction(ctx) is first and len(shared) == 1
    assert first.output_kind == 'metric_depth'
    np.testing.assert_array_equal(first.depth, load_predictor(path).predict(seq.frames[0].rgb))
    assert np.array_equal(get_method('single_view').fn(ctx).depth, first.depth)
    single_view_prediction(_ctx(seq, 1, shared, single_view=str(path)))
    assert len(shared) == 1  # the network is loaded once per run
    result = evaluate_sequence(
        seq, ['single_view', 'single_view_simulated'], ctx.options, show_progress=False
    )
    assert result.records['single_view'].all.summary()['n_pixels'] > 0


class _Relative(torch.nn.Module):
    """A stand-in network with an unscaled output (10 + the first normalised channel)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 10.0 + x[:, :1]


@pytest.mark.parametrize('kind', ['relative_depth', 'inverse_depth'])
def test_non_metric_outputs_are_median_scaled_for_scoring(tmp_path, kind):
    torch.jit.script(_Relative()).save(str(tmp_path / 'rel.pt'))
    write_metadata_yaml(
        ModelMetadata(input_width=64, input_height=48, output_kind=kind), tmp_path / 'rel.yaml'
    )
    seq = toy_sequence(1, 64, 48)
    ctx = _ctx(seq, 0, {}, single_view=str(tmp_path / 'rel.pt'))
    raw = single_view_prediction(ctx)
    assert raw.output_kind == kind and np.nanmedian(raw.depth) > 5  # handed on as it is
    out = get_method('single_view').fn(ctx)
    gt = seq.frames[0].depth
    valid = np.isfinite(gt)
    assert np.median(out.depth[valid]) == pytest.approx(np.median(gt[valid]), rel=1e-3)
    assert out.extras['median_scale'] > 0
