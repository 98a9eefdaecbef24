"""Single-view networks, checkpoints, TorchScript models and the predictor's preprocessing."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from depth_fusion_ros.metrics import frame_metrics
from depth_fusion_ros.singleview.architectures import build_model, count_parameters
from depth_fusion_ros.singleview.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from depth_fusion_ros.singleview.compact_net import CompactConfig, CompactDepthNet
from depth_fusion_ros.singleview.eigen_net import EigenConfig, EigenFergusNet
from depth_fusion_ros.singleview.metadata import ModelMetadata, read_metadata_yaml
from depth_fusion_ros.singleview.predictor import (
    DepthPredictor,
    default_model_path,
    load_predictor,
    predictor_from_network,
)
from depth_fusion_ros.singleview.torchscript_model import export_torchscript

pytestmark = pytest.mark.usefixtures('one_torch_thread')

TINY_COMPACT = {
    'input_width': 64,
    'input_height': 48,
    'encoder_widths': [8, 8, 16, 16, 16],
    'encoder_blocks': [0, 0, 0, 0, 0],
    'decoder_widths': [16, 16, 8, 8],
}
TINY_EIGEN = {
    'input_width': 96,
    'input_height': 72,
    'vgg_widths': [4, 4, 8, 8, 8],
    'fc_dim': 16,
    'coarse_channels': 4,
    'scale2_image_channels': 4,
    'scale2_channels': 4,
    'scale3_image_channels': 4,
    'scale3_channels': 4,
}


def _randomised(net: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Perturb every weight and BN statistic so round trips are tested on non-trivial values."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, t in net.state_dict().items():
            if t.is_floating_point():
                t.add_(0.05 * torch.randn(t.shape, generator=gen))
                if name.endswith('running_var'):
                    t.abs_().add_(0.1)
    return net.eval()


def _images(n: int, w: int, h: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def _meta(cfg: dict) -> ModelMetadata:
    return ModelMetadata(input_width=cfg['input_width'], input_height=cfg['input_height'])


def test_eigen_output_is_the_papers_147x109_for_304x228():
    """Eigen & Fergus' geometry: 9x9/2 conv + pool at scales 2/3 gives 147x109 from 304x228."""
    cfg = {**TINY_EIGEN, 'input_width': 304, 'input_height': 228}
    net = build_model('eigen', cfg).eval()
    with torch.no_grad():
        out = net(torch.zeros(1, 3, 228, 304))
    assert out.shape == (1, 1, 109, 147) and net.output_size == (109, 147)
    default = EigenConfig()
    assert default.vgg_out_size == (7, 9) and default.coarse_size == (14, 19)
    assert default.vgg_depths == (2, 2, 3, 3, 3) and default.vgg_widths == (64, 128, 256, 512, 512)


def test_compact_is_small_and_outputs_half_resolution():
    net = CompactDepthNet().eval()
    assert 1e5 < count_parameters(net) < 3e6
    with torch.no_grad():
        out = net(torch.zeros(2, 3, 240, 320))
    assert out.shape == (2, 1, 120, 160)
    assert torch.allclose(out.exp(), torch.full_like(out, 2.0), rtol=0.2)  # starts near 2 m


@pytest.mark.parametrize(('arch', 'cfg'), [('compact', TINY_COMPACT), ('eigen', TINY_EIGEN)])
def test_checkpoint_round_trip_gives_identical_outputs(tmp_path, arch, cfg):
    net = _randomised(build_model(arch, cfg))
    meta = _meta(cfg)
    meta.info['note'] = ('tuple', 1)
    path = save_checkpoint(tmp_path / 'm.pt', net, meta, training_state={'step': 3})
    ckpt = load_checkpoint(path)
    assert ckpt.architecture == arch and ckpt.training_state == {'step': 3}
    assert ckpt.metadata.info['note'] == ['tuple', 1]
    x = torch.randn(2, 3, cfg['input_height'], cfg['input_width'])
    with torch.no_grad():
        assert torch.equal(net(x), ckpt.model(x))
    # weights_only loading works: no pickled code in a checkpoint
    torch.load(path, weights_only=True)
    # through the predictor: identical depth maps
    images = _images(2, 80, 60)
    ours = predictor_from_network(net, meta).predict_batch(images)
    loaded = load_predictor(path).predict_batch(images)
    for a, b in zip(ours, loaded, strict=True):
        assert a.shape == (60, 80) and np.array_equal(a, b)


def test_half_precision_checkpoint_is_smaller_and_close(tmp_path):
    net = _randomised(CompactDepthNet())  # full size: the per-tensor overhead is negligible
    meta = ModelMetadata()
    full = save_checkpoint(tmp_path / 'full.pt', net, meta)
    half = save_checkpoint(tmp_path / 'half.pt', net, meta, half=True)
    assert half.stat().st_size < 0.6 * full.stat().st_size
    img = _images(1, 320, 240)[0]
    a, b = load_predictor(full).predict(img), load_predictor(half).predict(img)
    assert load_checkpoint(half).model.stem[0].weight.dtype == torch.float32
    np.testing.assert_allclose(a, b, rtol=1e-2)


def test_torchscript_export_and_import_give_identical_outputs(tmp_path):
    net = _randomised(build_model('compact', TINY_COMPACT))
    meta = _meta(TINY_COMPACT)
    pt, yml = export_torchscript(net, tmp_path / 'exported.pt', meta)
    assert yml == tmp_path / 'exported.yaml' and read_metadata_yaml(yml).output_kind == 'metric_depth'
    images = _images(3, 64, 48, seed=1)
    ours = predictor_from_network(net, meta).predict_batch(images)
    imported = load_predictor(pt)
    assert imported.output_kind == 'metric_depth'
    for a, b in zip(ours, imported.predict_batch(images), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


class _Probe(torch.nn.Module):
    """Returns the mean of its (preprocessed) input channels: a window onto preprocessing."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.mean(dim=(2, 3), keepdim=True)[:, :1] + x[:, 1:2] * 0


def test_metadata_drives_preprocessing_and_output(tmp_path):
    meta = ModelMetadata(
        input_width=32,
        input_height=16,
        mean=(0.5, 0.25, 0.0),
        std=(0.5, 0.5, 2.0),
        channel_order='bgr',
        output_kind='relative_depth',
        scale=10.0,
    )
    rgb = np.zeros((40, 60, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 255, 51, 102
    pred = DepthPredictor(_Probe(), meta)
    x = pred.preprocess([rgb])
    assert x.shape == (1, 3, 16, 32)
    # BGR order: channel 0 is blue (102/255), normalised with mean[0], std[0]
    np.testing.assert_allclose(
        x[0, :, 0, 0].numpy(), [(0.4 - 0.5) / 0.5, (0.2 - 0.25) / 0.5, 1.0 / 2.0], atol=1e-6
    )
    out = pred.predict(rgb)
    assert out.shape == (40, 60) and out.dtype == np.float32 and pred.output_kind == 'relative_depth'
    np.testing.assert_allclose(out, 10.0 * (0.4 - 0.5) / 0.5, atol=1e-5)  # times metadata scale
    # the same network as TorchScript + YAML behaves identically
    torch.jit.script(_Probe()).save(str(tmp_path / 'probe.pt'))
    (tmp_path / 'probe.yaml').write_text(yaml.safe_dump(meta.to_dict()))
    np.testing.assert_allclose(load_predictor(tmp_path / 'probe.pt').predict(rgb), out, atol=1e-6)
    # metric outputs are clamped to the declared depth range
    metric = DepthPredictor(
        _Probe(), ModelMetadata(input_width=8, input_height=8, depth_min=0.5, mean=(0, 0, 0))
    )
    assert metric.predict(np.zeros((8, 8, 3), np.uint8)).min() == pytest.approx(0.5)


@pytest.mark.parametrize(
    'bad',
    [
        np.zeros((10, 10), np.uint8),
        np.zeros((10, 10, 4), np.uint8),
        np.zeros((10, 10, 3), np.float32),
        'not an image',
    ],
)
def test_non_rgb_input_raises_clear_error(bad):
    pred = predictor_from_network(build_model('compact', TINY_COMPACT), _meta(TINY_COMPACT))
    with pytest.raises(ValueError, match=r'RGB|uint8|numpy'):
        pred.predict(bad)


def test_bad_checkpoints_fail_at_load_with_the_file_name(tmp_path):
    with pytest.raises(FileNotFoundError, match=r'nowhere\.pt'):
        load_predictor(tmp_path / 'nowhere.pt')
    corrupt = tmp_path / 'corrupt.pt'
    corrupt.write_bytes(b'\x00garbage' * 100)
    with pytest.raises(CheckpointError, match=r'corrupt\.pt'):
        load_predictor(corrupt)
    good = save_checkpoint(tmp_path / 'good.pt', build_model('compact', TINY_COMPACT), _meta(TINY_COMPACT))
    truncated = tmp_path / 'truncated.pt'
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=r'truncated\.pt'):
        load_predictor(truncated)
    foreign = tmp_path / 'foreign.pt'
    torch.save({'weights': torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match=r'foreign\.pt.*missing'):
        load_predictor(foreign)
    doc = torch.load(good, weights_only=True)
    doc['arch_config'] = {**TINY_COMPACT, 'decoder_widths': [16, 16, 8, 12]}
    mismatched = tmp_path / 'mismatched.pt'
    torch.save(doc, mismatched)
    with pytest.raises(CheckpointError, match=r'mismatched\.pt.*do not match'):
        load_predictor(mismatched)
    doc = torch.load(good, weights_only=True)
    doc['metadata']['output_kind'] = 'disparity'
    torch.save(doc, tmp_path / 'badmeta.pt')
    with pytest.raises(CheckpointError, match=r'badmeta\.pt.*output_kind'):
        load_predictor(tmp_path / 'badmeta.pt')


def test_torchscript_metadata_errors_name_the_file(tmp_path):
    torch.jit.script(_Probe()).save(str(tmp_path / 'net.pt'))
    with pytest.raises(FileNotFoundError, match=r'net\.yaml'):
        load_predictor(tmp_path / 'net.pt')
    (tmp_path / 'net.yaml').write_text('input_width: 32\ninput_height: [16\n')
    with pytest.raises(ValueError, match=r'net\.yaml line \d'):
        load_predictor(tmp_path / 'net.pt')
    (tmp_path / 'net.yaml').write_text('input_width: 32\ninput_hieght: 16\n')
    with pytest.raises(ValueError, match=r'net\.yaml.*input_hieght'):
        load_predictor(tmp_path / 'net.pt')
    (tmp_path / 'net.yaml').write_text('output_kind: disparity\n')
    with pytest.raises(ValueError, match=r'net\.yaml.*output_kind'):
        load_predictor(tmp_path / 'net.pt')
    with pytest.raises(CheckpointError, match=r'TorchScript'):
        load_checkpoint(tmp_path / 'net.pt')


def test_load_predictor_rejects_simulated_and_bad_devices():
    with pytest.raises(ValueError, match=r'evaluation-only'):
        load_predictor('simulated')
    with pytest.raises(ValueError, match=r'device'):
        load_predictor('default', device='gpu0')


def test_unknown_architecture_and_config_fields():
    with pytest.raises(ValueError, match=r'unknown architecture'):
        build_model('resnet')
    with pytest.raises(ValueError, match=r'widths'):
        CompactConfig.from_dict({'widths': 3})
    assert isinstance(build_model('eigen', TINY_EIGEN), EigenFergusNet)


def test_shipped_model_is_small_synthetic_only_and_better_than_a_constant(synthetic_sequence):
    """The committed default model: <= 10 MB, trained on the project's synthetic rooms only,
    and on an unseen synthetic room clearly better than each frame's median depth."""
    path = default_model_path()
    assert path.is_file() and path.stat().st_size <= 10e6
    info = load_checkpoint(path).metadata.info
    assert info['training_sources'] and all(s.startswith('Synthetic room') for s in info['training_sources'])
    assert not any('shared' in s for s in info['training_sequences'])
    predictor = load_predictor('default')
    assert predictor.output_kind == 'metric_depth' and predictor.input_size == (320, 240)
    for i in (0, 12):
        frame = synthetic_sequence.frames[i]
        depth = predictor.predict(frame.rgb)
        assert depth.shape == frame.rgb.shape[:2] and np.isfinite(depth).all()
        constant = np.full_like(frame.depth, np.nanmedian(frame.depth))
        assert frame_metrics(depth, frame.depth)['mae'] < 0.8 * frame_metrics(constant, frame.depth)['mae']


def test_shipped_model_scale_barely_moves_with_the_cameras_focal_length():
    """Another lens does not rescale the shipped network's depth: on unseen synthetic rooms
    seen with 0.5x to 2x its training focal length, its median depth / truth stays within
    0.75-1.3 (a network that judged depth by apparent size alone would give 2.0-0.5). So no
    focal-length factor is applied to its output; one was tried and made the depth worse
    (docs/single_view.md, "Another camera's focal length")."""
    from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence

    predictor = load_predictor('default')
    focal = load_checkpoint(default_model_path()).metadata.info['training_focal_px']
    for scale in (0.5, 2.0):
        seq = render_sequence(
            SynthConfig(width=320, height=240, frames=1, seed=5, fx=focal * scale, fy=focal * scale)
        )
        gt = seq.gt_depth_working(0)
        ok = np.isfinite(gt) & (gt > 0)
        ratio = float(np.median(predictor.predict(seq.frames[0].rgb)[ok] / gt[ok]))
        assert 0.75 <= ratio <= 1.3, (scale, ratio)
