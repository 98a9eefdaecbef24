"""Training: losses, augmentation geometry, a short run that learns, determinism and resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from test_singleview_toy import toy_samples

from depth_fusion_ros.singleview.augment import AugmentConfig, augment_batch, zoom_crop
from depth_fusion_ros.singleview.checkpoint import load_checkpoint
from depth_fusion_ros.singleview.losses import (
    depth_loss,
    gradient_loss,
    log_depth_target,
    scale_invariant_loss,
)
from depth_fusion_ros.singleview.training import TrainConfig, learning_rate, train_model
from depth_fusion_ros.singleview.training_data import DepthSamples, split_validation

pytestmark = pytest.mark.usefixtures('one_torch_thread')

TINY = {
    'input_width': 64,
    'input_height': 48,
    'encoder_widths': [8, 8, 16, 16, 16],
    'encoder_blocks': [0, 0, 0, 0, 0],
    'decoder_widths': [16, 16, 8, 8],
}


def test_scale_invariant_and_gradient_losses():
    gt = torch.rand(2, 1, 12, 16) * 3 + 0.5
    gt[0, 0, 0, :5] = float('nan')
    log_gt, valid = log_depth_target(gt)
    assert not valid[0, 0, 0, :5].any() and valid.sum() == 2 * 12 * 16 - 5
    log_scaled = log_gt + np.log(1.7)  # prediction = 1.7 x truth
    assert float(scale_invariant_loss(log_scaled, log_gt, valid, lam=1.0)) == pytest.approx(0, abs=1e-6)
    assert float(scale_invariant_loss(log_scaled, log_gt, valid, lam=0.5)) == pytest.approx(
        0.5 * np.log(1.7) ** 2, rel=1e-4
    )
    assert float(gradient_loss(log_scaled, log_gt, valid)) == pytest.approx(0, abs=1e-6)
    bumpy = log_gt.clone()
    bumpy[..., ::2] += 0.1
    assert float(gradient_loss(bumpy, log_gt, valid)) > 0.005
    # NaN ground truth never leaks into the loss
    assert torch.isfinite(depth_loss(torch.zeros(2, 1, 6, 8), gt))


def test_zoom_crop_divides_depth_by_the_zoom():
    """Zooming by s is a camera with focal s·f: the same image as depth z/s with focal f."""
    rgb = torch.rand(1, 3, 48, 64)
    depth = torch.full((1, 1, 48, 64), 3.0)
    depth[..., :4, :4] = float('nan')
    out_rgb, out_depth = zoom_crop(rgb, depth, torch.tensor([2.0]), torch.tensor([0.0]), torch.tensor([0.0]))
    assert out_rgb.shape == rgb.shape
    assert torch.isnan(out_depth[..., :8, :8]).all()  # the hole is magnified, not blended
    finite = out_depth[torch.isfinite(out_depth)]
    assert torch.allclose(finite, torch.tensor(1.5))


def test_augmentation_keeps_rgb_and_depth_aligned():
    """Colour encodes depth before augmentation; flips and crops must keep that relation."""
    gen = torch.Generator().manual_seed(3)
    depth = torch.rand(4, 1, 48, 64) * 2 + 1
    rgb = (depth / 4).expand(4, 3, 48, 64).clone()
    cfg = AugmentConfig(max_zoom=1.0, flip=True, jitter=0.0)
    out_rgb, out_depth = augment_batch(rgb, depth, cfg, gen)
    assert torch.allclose(out_rgb[:, :1] * 4, out_depth)
    assert not torch.equal(out_depth, depth)  # some images were flipped


def test_learning_rate_schedule():
    cfg = TrainConfig(steps=100, lr=1e-3, warmup_steps=10, min_lr_ratio=0.1)
    assert learning_rate(cfg, 0) == pytest.approx(1e-4)
    assert learning_rate(cfg, 10) == pytest.approx(1e-3)
    assert learning_rate(cfg, 100) == pytest.approx(1e-4)


def test_split_validation_holds_out_whole_sequences():
    parts = [toy_samples(4, 64, 48, seed=s) for s in range(5)]
    train, val = split_validation(parts, 0.2)
    assert len(train) == 16 and len(val) == 4 and val.sequences == ['toy4']
    train, val = split_validation(parts[:1], 0.25, gap=1)
    assert len(train) == 2 and len(val) == 1
    with pytest.raises(ValueError, match='fraction'):
        split_validation(parts, 1.5)


def _cfg(**kw) -> TrainConfig:
    base = dict(
        arch_config=TINY, steps=60, batch_size=8, lr=3e-3, val_every=20, warmup_steps=5, val_max_samples=12
    )
    return TrainConfig(**{**base, **kw})


def test_short_training_run_lowers_the_loss(tmp_path):
    train, val = toy_samples(48, 64, 48, seed=0), toy_samples(12, 64, 48, seed=1)
    result = train_model(train, val, _cfg(), tmp_path, show_progress=False, extra_info={'note': 'toy'})
    hist = result.history
    assert [h['step'] for h in hist] == [0, 20, 40, 60]
    assert hist[-1]['val']['loss'] < 0.7 * hist[0]['val']['loss']
    assert hist[-1]['val']['mae'] < hist[0]['val']['mae']
    assert hist[-1]['train_loss'] < hist[1]['train_loss']
    assert (tmp_path / 'curve.png').stat().st_size > 0
    assert json.loads((tmp_path / 'history.json').read_text())[-1]['step'] == 60
    best = load_checkpoint(result.best_path)
    assert best.metadata.info['note'] == 'toy' and best.metadata.info['seed'] == 0
    assert best.metadata.info['metrics']['mae'] == pytest.approx(result.best_metrics['mae'])
    assert best.training_state is None and load_checkpoint(result.last_path).training_state['step'] == 60


def test_training_is_deterministic_and_resume_is_exact(tmp_path):
    train = toy_samples(16, 64, 48, seed=0)
    val = toy_samples(4, 64, 48, seed=1)
    cfg = _cfg(steps=12, val_every=4, batch_size=4)
    whole = train_model(train, val, cfg, tmp_path / 'whole', show_progress=False)
    train_model(train, val, cfg, tmp_path / 'chunks', stop_at=8, show_progress=False)
    with pytest.raises(ValueError, match='--resume'):
        train_model(train, val, cfg, tmp_path / 'chunks', show_progress=False)
    resumed = train_model(train, val, cfg, tmp_path / 'chunks', resume=True, show_progress=False)
    a = load_checkpoint(whole.last_path).model.state_dict()
    b = load_checkpoint(resumed.last_path).model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert [h['val']['loss'] for h in whole.history] == [h['val']['loss'] for h in resumed.history]
    other = train_model(train, val, _cfg(steps=4, val_every=4, batch_size=4, seed=1), tmp_path / 'seed1',
                        show_progress=False)  # fmt: skip
    assert other.history[-1]['val']['loss'] != whole.history[1]['val']['loss']
    with pytest.raises(ValueError, match='cannot resume'):
        train_model(train, val, _cfg(arch_config={**TINY, 'decoder_widths': [16, 16, 8, 4]}, steps=12),
                    tmp_path / 'chunks', resume=True, show_progress=False)  # fmt: skip


def test_mismatched_sample_size_is_refused(tmp_path):
    samples = DepthSamples.concat([toy_samples(4, 32, 32)])
    with pytest.raises(ValueError, match='network takes'):
        train_model(samples, None, _cfg(), tmp_path, show_progress=False)


def test_eigen_network_trains_too(tmp_path):
    """The paper's three-scale architecture (reduced widths) learns through the same loop."""
    tiny_eigen = {
        'input_width': 96,
        'input_height': 72,
        'vgg_widths': [4, 8, 8, 16, 16],
        'fc_dim': 32,
        'coarse_channels': 4,
        'scale2_image_channels': 8,
        'scale2_channels': 8,
        'scale3_image_channels': 8,
        'scale3_channels': 8,
    }
    train, val = toy_samples(32, 96, 72, seed=0), toy_samples(8, 96, 72, seed=1)
    cfg = _cfg(architecture='eigen', arch_config=tiny_eigen, steps=20, val_every=20, lr=2e-3)
    hist = train_model(train, val, cfg, tmp_path, show_progress=False).history
    assert hist[-1]['val']['loss'] < 0.7 * hist[0]['val']['loss']
