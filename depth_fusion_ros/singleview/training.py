"""Training loop for the single-view networks (``depth-fusion train`` calls ``train_model``).

Loss: Eigen's scale-invariant loss on log depth plus the gradient-matching term
(``losses.py``); augmentation: zoom crops that keep the intrinsics consistent, flips and
colour jitter (``augment.py``); AdamW with warm-up and cosine decay.

Reproducibility: every random choice of step ``k`` (which samples, which augmentation,
dropout) is drawn from generators seeded with ``(seed, k)``, and the learning rate is a pure
function of ``k``. So a run is deterministic for a seed on one device, and resuming from
``last.pt`` (weights + optimizer state + step) continues exactly where it stopped.

Outputs in ``out_dir``: ``last.pt`` (checkpoint with ``training_state``, for resume),
``best.pt`` (lowest validation MAE, no training state), ``history.json`` (loss and
validation metrics per evaluation), and ``curve.png``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ..metrics import MetricAccumulator
from ..progress import progress
from .architectures import build_model, count_parameters, model_input_size
from .augment import AugmentConfig, augment_batch
from .checkpoint import load_checkpoint, save_checkpoint
from .losses import depth_loss, upsample_to
from .metadata import IMAGENET_MEAN, IMAGENET_STD, ModelMetadata
from .predictor import resolve_device
from .training_data import DepthSamples

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Everything that defines a training run (stored in the checkpoint's metadata)."""

    architecture: str = 'compact'
    arch_config: dict[str, Any] = field(default_factory=dict)
    steps: int = 2000
    batch_size: int = 8
    lr: float = 1e-3
    #: The cosine schedule ends at ``lr · min_lr_ratio``.
    min_lr_ratio: float = 0.05
    warmup_steps: int = 50
    weight_decay: float = 1e-4
    si_lambda: float = 0.5
    grad_weight: float = 1.0
    grad_clip: float = 5.0
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    #: Evaluate on the validation set every ``val_every`` steps (and at the end).
    val_every: int = 200
    #: Evaluate on at most this many validation samples (evenly spaced), to keep it cheap.
    val_max_samples: int = 120
    seed: int = 0
    device: str = 'cpu'

    def validate(self) -> None:
        for name in ('steps', 'batch_size', 'val_every', 'val_max_samples'):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f'{name} must be positive, got {getattr(self, name)}')
        if not self.lr > 0:
            raise ValueError(f'lr must be positive, got {self.lr}')
        self.augment.validate()

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class TrainResult:
    history: list[dict[str, Any]]
    last_path: Path
    best_path: Path | None
    best_metrics: dict[str, float]


def learning_rate(cfg: TrainConfig, step: int) -> float:
    """Linear warm-up then cosine decay to ``lr · min_lr_ratio`` (a function of the step only)."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    t = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    floor = cfg.lr * cfg.min_lr_ratio
    return floor + (cfg.lr - floor) * 0.5 * (1 + math.cos(math.pi * min(1.0, t)))


def git_commit() -> str:
    """The commit of the code that trained the model (provenance), or 'unknown'."""
    try:
        out = subprocess.run(
            ['git', 'rev-parse', '--short', 'HEAD'],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
        )
        return out.stdout.strip() or 'unknown'
    except (OSError, subprocess.SubprocessError):
        return 'unknown'


def to_network_input(rgb: torch.Tensor) -> torch.Tensor:
    """[0, 1] RGB (B, 3, H, W) -> ImageNet-normalised, as ``ModelMetadata`` defaults say."""
    mean = torch.tensor(IMAGENET_MEAN, device=rgb.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=rgb.device).view(1, 3, 1, 1)
    return (rgb - mean) / std


def batch_tensors(
    samples: DepthSamples, idx: np.ndarray, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """(rgb in [0, 1] (B, 3, H, W), depth (B, 1, H, W) float32) on ``device``."""
    rgb = torch.from_numpy(samples.rgb[idx]).to(device).permute(0, 3, 1, 2).float() / 255.0
    depth = torch.from_numpy(samples.depth[idx].astype(np.float32)).to(device)[:, None]
    return rgb, depth


@torch.no_grad()
def evaluate_model(
    model: nn.Module, samples: DepthSamples, cfg: TrainConfig, device: torch.device, batch_size: int = 8
) -> dict[str, float]:
    """Validation loss and the project's depth metrics (``metrics.py``) at the input size."""
    was_training = model.training
    model.eval()
    n = len(samples)
    picks = np.unique(np.linspace(0, n - 1, min(n, cfg.val_max_samples)).round().astype(int))
    acc = MetricAccumulator()
    losses = []
    for start in range(0, len(picks), batch_size):
        idx = picks[start : start + batch_size]
        rgb, depth = batch_tensors(samples, idx, device)
        log_pred = model(to_network_input(rgb))
        losses.append(float(depth_loss(log_pred, depth, cfg.si_lambda, cfg.grad_weight)) * len(idx))
        pred = upsample_to(log_pred, tuple(depth.shape[-2:])).exp().cpu().numpy()
        gt = depth.cpu().numpy()
        for p, g in zip(pred[:, 0], gt[:, 0], strict=True):
            acc.add(p, g)
    model.train(was_training)
    summary = acc.summary()
    out = {k: float(summary[k]) for k in ('mae', 'rmse', 'si', 'abs_rel', 'delta1')}
    out['loss'] = float(sum(losses) / len(picks))
    return out


def model_metadata(
    model: nn.Module, train: DepthSamples, cfg: TrainConfig, extra_info: dict[str, Any]
) -> ModelMetadata:
    """Metadata of a trained model: input contract + provenance (data, commit, seed, config)."""
    width, height = model_input_size(model)
    finite = train.depth[np.isfinite(train.depth)].astype(np.float32)
    deepest = float(np.percentile(finite, 99.9)) if finite.size else 10.0
    info = {
        'architecture': model.architecture,
        'parameters': count_parameters(model),
        'training_sequences': list(train.sequences),
        'training_samples': len(train),
        'training_focal_px': float(np.mean(train.focal_px)) if train.focal_px else None,
        'git_commit': git_commit(),
        'seed': cfg.seed,
        'train_config': cfg.to_dict(),
        **extra_info,
    }
    return ModelMetadata(
        input_width=width,
        input_height=height,
        output_kind='metric_depth',
        depth_min=0.1,
        depth_max=max(10.0, round(1.5 * deepest, 1)),
        info=info,
    )


def _write_history(out_dir: Path, history: list[dict[str, Any]], figure: bool = False) -> None:
    (out_dir / 'history.json').write_text(json.dumps(history, indent=1))
    if not figure:
        return
    try:
        plot_history(history, out_dir / 'curve.png')
    except Exception as exc:  # a figure must never kill a training run
        log.warning('could not draw the training curve: %s', exc)


def plot_history(history: list[dict[str, Any]], path: Path) -> None:
    """Loss and validation MAE against the step (``Figure`` directly: no pyplot backend state)."""
    from matplotlib.figure import Figure

    steps = [h['step'] for h in history]
    val_steps = [h['step'] for h in history if 'val' in h]
    fig = Figure(figsize=(9, 3.2))
    ax_loss, ax_mae = fig.subplots(1, 2)
    ax_loss.plot(steps, [h['train_loss'] for h in history], label='train loss')
    ax_loss.plot(val_steps, [h['val']['loss'] for h in history if 'val' in h], 'o-', label='val loss')
    ax_mae.plot(val_steps, [h['val']['mae'] for h in history if 'val' in h], 'o-', label='val MAE (m)')
    for ax in (ax_loss, ax_mae):
        ax.set_xlabel('step')
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


@dataclass
class _RunState:
    """What a training run carries from step to step (and through ``last.pt``)."""

    model: nn.Module
    opt: torch.optim.Optimizer
    step: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)
    best_mae: float = math.inf


def _restore(state: _RunState, last_path: Path, cfg: TrainConfig, device: torch.device) -> None:
    """Load weights, optimizer state, step and history of ``last_path`` into ``state``."""
    if not last_path.is_file():
        raise FileNotFoundError(f'cannot resume: {last_path} does not exist')
    ckpt = load_checkpoint(last_path, device)
    if ckpt.architecture != cfg.architecture or ckpt.arch_config != build_model_config(cfg):
        raise ValueError(
            f'{last_path}: was trained as {ckpt.architecture} {ckpt.arch_config}, '
            f'cannot resume as {cfg.architecture} {build_model_config(cfg)}'
        )
    saved = ckpt.training_state
    if not saved:
        raise ValueError(f'{last_path}: has no training_state to resume from')
    previous = ckpt.metadata.info.get('train_config', {})
    changed = sorted(k for k, v in cfg.to_dict().items() if k in previous and previous[k] != v)
    if changed:
        log.warning('resuming with changed settings %s: the run is no longer one reproducible run', changed)
    state.model.load_state_dict(ckpt.model.state_dict())
    state.opt.load_state_dict(saved['optimizer'])
    state.step, state.history = int(saved['step']), list(saved['history'])
    state.best_mae = float(saved['best_mae'])
    log.info('resuming %s at step %d of %d', last_path, state.step, cfg.steps)


def build_model_config(cfg: TrainConfig) -> dict[str, Any]:
    """The full arch_config (defaults filled in) that ``cfg`` builds."""
    from .architectures import arch_config_class

    return arch_config_class(cfg.architecture).from_dict(dict(cfg.arch_config)).to_dict()


def _train_step(state: _RunState, train: DepthSamples, cfg: TrainConfig, device: torch.device) -> float:
    """One optimiser step; every random draw is seeded by ``(seed, step)``."""
    step = state.step
    for group in state.opt.param_groups:
        group['lr'] = learning_rate(cfg, step)
    rng = np.random.default_rng([cfg.seed, step])
    gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
    torch.manual_seed(cfg.seed * 7_919 + step)  # dropout (Eigen's fully connected layers)
    idx = np.sort(rng.choice(len(train), size=min(cfg.batch_size, len(train)), replace=False))
    rgb, depth = batch_tensors(train, idx, device)
    rgb, depth = augment_batch(rgb, depth, cfg.augment, gen)
    loss = depth_loss(state.model(to_network_input(rgb)), depth, cfg.si_lambda, cfg.grad_weight)
    state.opt.zero_grad(set_to_none=True)
    loss.backward()
    if cfg.grad_clip > 0:
        nn.utils.clip_grad_norm_(state.model.parameters(), cfg.grad_clip)
    state.opt.step()
    state.step += 1
    return float(loss.detach())


def _record(
    state: _RunState,
    entry: dict[str, Any],
    val: DepthSamples | None,
    cfg: TrainConfig,
    device: torch.device,
    meta: ModelMetadata,
    out_dir: Path,
) -> None:
    """Validate, append to the history, save ``best.pt`` when better and ``last.pt`` always."""
    if val is not None and len(val):
        entry['val'] = evaluate_model(state.model, val, cfg, device)
        v = entry['val']
        log.info(
            'step %d: train loss %.4f, val loss %.4f, MAE %.3f m, si %.4f, δ1 %.3f',
            entry['step'], entry['train_loss'], v['loss'], v['mae'], v['si'], v['delta1'],
        )  # fmt: skip
    state.history.append(entry)
    score = entry.get('val', {}).get('mae', entry['train_loss'])
    meta.info.update(step=state.step, metrics=entry.get('val', {}))
    if state.step > 0 and score < state.best_mae:
        state.best_mae = score
        save_checkpoint(out_dir / 'best.pt', state.model, meta)
    training_state = {
        'step': state.step,
        'optimizer': state.opt.state_dict(),
        'history': state.history,
        'best_mae': state.best_mae,
    }
    save_checkpoint(out_dir / 'last.pt', state.model, meta, training_state=training_state)
    _write_history(out_dir, state.history)


def train_model(
    train: DepthSamples,
    val: DepthSamples | None,
    cfg: TrainConfig,
    out_dir: str | Path,
    *,
    resume: bool = False,
    stop_at: int | None = None,
    show_progress: bool = True,
    extra_info: dict[str, Any] | None = None,
) -> TrainResult:
    """Train ``cfg.architecture`` on ``train``, validating on ``val``; checkpoints go to ``out_dir``.

    ``stop_at`` ends the run after that step (saved, resumable) without changing the
    schedule of ``cfg.steps``: a long run can be done in chunks (``resume=True`` continues).
    A fresh run first records the untrained network's validation error (step 0).
    """
    cfg.validate()
    if len(train) == 0:
        raise ValueError('no training samples')
    device = resolve_device(cfg.device)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    last_path = out_dir / 'last.pt'

    torch.manual_seed(cfg.seed)
    model = build_model(cfg.architecture, cfg.arch_config).to(device)
    if model_input_size(model) != train.size:
        raise ValueError(
            f'samples are {train.size} but the {cfg.architecture} network takes {model_input_size(model)}'
        )
    state = _RunState(model, torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay))
    if resume:
        _restore(state, last_path, cfg, device)
    elif last_path.exists():
        raise ValueError(f'{last_path} exists: pass --resume to continue it, or choose another output folder')
    meta = model_metadata(model, train, cfg, dict(extra_info or {}))
    log.info(
        '%s network, %d parameters, %d training / %d validation samples, %d steps on %s',
        cfg.architecture, count_parameters(model), len(train), len(val) if val else 0, cfg.steps, device,
    )  # fmt: skip
    if state.step == 0:
        _record(
            state,
            {'step': 0, 'train_loss': float('nan'), 'lr': 0.0, 'seconds': 0.0},
            val,
            cfg,
            device,
            meta,
            out_dir,
        )
    end = min(cfg.steps, stop_at) if stop_at is not None else cfg.steps
    model.train()
    window: list[float] = []
    t0 = time.perf_counter() - (state.history[-1]['seconds'] if state.history else 0.0)
    bar = progress(range(state.step, end), desc='train', unit='step', disable=not show_progress)
    for _ in bar:
        window.append(_train_step(state, train, cfg, device))
        if hasattr(bar, 'set_postfix'):
            bar.set_postfix(loss=f'{np.mean(window[-20:]):.4f}')
        if state.step % cfg.val_every == 0 or state.step == end:
            entry = {
                'step': state.step,
                'train_loss': float(np.mean(window)),
                'lr': learning_rate(cfg, state.step - 1),
                'seconds': time.perf_counter() - t0,
            }
            window = []
            _record(state, entry, val, cfg, device, meta, out_dir)
    if state.history:
        _write_history(out_dir, state.history, figure=True)
    best_path = out_dir / 'best.pt'
    trained = [h['val'] for h in state.history if 'val' in h and h['step'] > 0]
    best = min(trained, key=lambda v: v['mae'], default={})
    return TrainResult(state.history, last_path, best_path if best_path.is_file() else None, best)


def ship_checkpoint(src: str | Path, dst: str | Path, extra_info: dict[str, Any] | None = None) -> Path:
    """Copy a trained checkpoint without its training state and with float16 weights (half
    the size), the form committed under ``depth_fusion_ros/models/``; also writes the
    metadata as YAML beside it for people to read."""
    from .metadata import write_metadata_yaml

    ckpt = load_checkpoint(src)
    meta = ckpt.metadata
    meta.info.update(extra_info or {})
    path = save_checkpoint(dst, ckpt.model, meta, half=True)
    write_metadata_yaml(meta, Path(dst).with_suffix('.yaml'))
    return path
