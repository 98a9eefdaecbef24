"""The Adapter: trains the network on each new keyframe (plus replay), guarded, versioned.

``observe(sample)`` is one update: check the guard (held-out multi-view points of this and
recent keyframes), take ``steps_per_keyframe`` Adam steps on the self-supervised loss over
the new keyframe and ``replay_per_step`` replayed ones, check the guard again and roll the
weights *and the optimiser state* back if it got worse. Accepted updates bump ``version``.

The adapter owns its training copy of the network; whoever runs inference gets copies of
accepted weights (``inference_network``), so training never mutates a module that is
predicting. Prequential use (offline evaluation): predict keyframe k with the current
weights, then ``observe`` it.

``restart`` starts the training over from the loaded weights, with an empty replay and a
fresh optimiser: the node calls it when the poses every earlier training signal was computed
from turn out to be another frame's (docs/adaptation.md, "A frame turn starts the training
over").

Only ``observe`` and ``restart`` change ``net``: the guard's per-keyframe errors are kept for
the weights they were computed with (a token), so writing into ``net`` from outside would
leave them stale.
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ..compile_lock import COMPILE_LOCK
from ..singleview.metadata import ModelMetadata
from ..singleview.predictor import DepthPredictor, predictor_from_network, resolve_device
from .batch import batch_loss
from .config import AdaptConfig
from .guard import GuardVerdict, guard_point_errors, judge
from .inference_copies import InferenceCopies
from .prepared import PreparedSample
from .replay import ReplayBuffer
from .sample import AdaptSample
from .snapshot import WeightSnapshot
from .window import draw_windows

log = logging.getLogger(__name__)

STATUSES = ('updated', 'rolled_back', 'skipped', 'restarted')


@dataclass
class UpdateReport:
    """What one ``observe`` did."""

    key: int
    status: str
    reason: str = ''
    steps: int = 0
    loss_first: float = float('nan')
    loss_last: float = float('nan')
    guard: GuardVerdict | None = None
    version: int = 0
    seconds: float = 0.0
    photometric: bool = False
    #: Trained with ``steps_when_behind`` steps.
    behind: bool = False


@dataclass
class AdapterCounters:
    observed: int = 0
    updated: int = 0
    rolled_back: int = 0
    skipped: int = 0
    steps: int = 0
    #: Updates trained with ``steps_when_behind`` steps (kept or rolled back).
    behind: int = 0
    #: Times the training started over from the loaded weights (:meth:`Adapter.restart`).
    restarts: int = 0
    train_seconds: float = 0.0
    reasons: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.__dict__.items()}

    def skip(self, reason: str) -> None:
        """Count a keyframe not trained on, under its short reason (``too_few_points``, ``stopped``, ...)."""
        self.skipped += 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1


def load_adaptable(
    spec: str | Path, device: str | torch.device = 'cpu'
) -> tuple[nn.Module, ModelMetadata, str]:
    """The network, metadata and name of an adaptable ``spec`` ('default' or a checkpoint of
    ``depth-fusion train`` / ``adapt``); a one-line error for anything else (an exported model,
    a missing file, the simulated prior). The in-process and the process-backed adapter
    (``remote_adapter.py``) both load through it, so they refuse the same models."""
    from ..singleview.checkpoint import is_exported_model, load_checkpoint
    from ..singleview.predictor import SIMULATED_SPEC, model_path

    if str(spec) == SIMULATED_SPEC:
        raise ValueError("adaptation needs a network: 'simulated' is the evaluation-only prior")
    path = model_path(spec)
    if not path.is_file():
        raise FileNotFoundError(f'single-view model not found: {path}')
    if is_exported_model(path):
        raise ValueError(
            f"{path}: adaptation trains the project's own networks (checkpoints of depth-fusion "
            'train/adapt, or the shipped model); an exported ONNX / .pt2 / TorchScript model '
            'cannot be adapted'
        )
    ckpt = load_checkpoint(path, device)
    return ckpt.model, ckpt.metadata, f'{ckpt.architecture}:{path.name}'


def _output_bias(net: nn.Module) -> list[nn.Parameter]:
    """The network's final scalar bias (a global log-depth offset), if it has one."""
    scalars = [(n, p) for n, p in net.named_parameters() if p.numel() == 1 and n.endswith('bias')]
    return [scalars[-1][1]] if scalars else []


@contextlib.contextmanager
def _cudnn_disabled() -> Iterator[None]:
    """cuDNN off, and back as it was (only that flag: ``cudnn.flags`` resets its others too)."""
    was = torch.backends.cudnn.enabled
    torch.backends.cudnn.enabled = False
    try:
        yield
    finally:
        torch.backends.cudnn.enabled = was


class Adapter:
    """Online self-supervised training of one of our log-depth networks."""

    def __init__(
        self,
        net: nn.Module,
        metadata: ModelMetadata,
        config: AdaptConfig | None = None,
        device: str | torch.device = 'cpu',
        name: str = '',
    ):
        self.config = config or AdaptConfig()
        self.config.validate()
        self.device = resolve_device(device)
        self.metadata = metadata
        self.name = name or getattr(net, 'architecture', type(net).__name__)
        self.net = copy.deepcopy(net).to(self.device)
        self._set_train_mode()
        bias = _output_bias(self.net)
        bias_ids = {id(p) for p in bias}
        groups = [
            {'params': [p for p in self.net.parameters() if id(p) not in bias_ids], 'lr': self.config.lr}
        ]
        if bias and self.config.scale_lr > 0:
            groups.append({'params': bias, 'lr': self.config.scale_lr})
        self._groups = groups
        self._snapshot: WeightSnapshot | None = None  # holds the optimiser, built on first use
        #: The loaded weights: what the anchor holds to and what a restart goes back to.
        self._start_net = copy.deepcopy(self.net).eval().requires_grad_(False)
        self.buffer: ReplayBuffer[PreparedSample] = ReplayBuffer(self.config.buffer_size)
        self.counters = AdapterCounters()
        self.version = 0
        #: Updates accepted since the start or the last restart (the start coverage applies
        #: again after a restart: the weights are the loaded ones).
        self.accepted = 0
        self._copies = InferenceCopies(self.net)
        # Names the current weights: guard errors computed under a token stay valid while it
        # is current (a rollback restores the token of the weights it restores).
        self._tokens = itertools.count(1)
        self._token = 0
        # Preprocessing (resize, normalisation) exactly as the inference predictor does it.
        self._preprocessor = predictor_from_network(nn.Identity(), metadata, self.device)

    def _built(self) -> WeightSnapshot:
        """The rollback snapshot of the weights and of the optimiser's state, with the optimiser
        (Adam over the network's parameter groups), built on first use (:meth:`warm_up`).

        Building any torch optimiser imports ``torch._dynamo`` (``Optimizer.__init__`` is
        wrapped by ``torch._disable_dynamo``): 3.6 s of a 2-core CPU, which the single-view
        node spent in its constructor, before it was ready. Its training thread now builds it,
        off the inference path. ``foreach``: one grouped kernel per update rule instead of one
        per parameter (the default on CUDA already; on the CPU it halves the step's optimiser
        time). Built holding ``COMPILE_LOCK``: that import must not race another thread's first
        import of the compiler (compile_lock.py; the fusion node's compile in the composed graph).
        """
        snapshot = self._snapshot
        if snapshot is not None:
            return snapshot
        with COMPILE_LOCK:  # also one build only, whichever thread asks first
            if self._snapshot is None:
                self._snapshot = WeightSnapshot(self.net, torch.optim.Adam(self._groups, foreach=True))
            return self._snapshot

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        return self._built().optimizer

    @property
    def _weights(self) -> WeightSnapshot:
        return self._built()

    def warm_up(self) -> None:
        """Pay the optimiser's first-use cost now (the training thread calls it at start)."""
        self._built()

    # --- construction -------------------------------------------------------------------------

    @classmethod
    def from_spec(
        cls, spec: str | Path, config: AdaptConfig | None = None, device: str | torch.device = 'cpu'
    ) -> Adapter:
        """An adapter for the network named like ``load_predictor``'s ``spec`` ('default' or a
        checkpoint of ``depth-fusion train`` / ``adapt``). Exported models cannot adapt."""
        net, metadata, name = load_adaptable(spec, device)
        return cls(net, metadata, config, device, name=name)

    # --- inference side -----------------------------------------------------------------------

    def inference_network(self) -> nn.Module:
        """A detached eval-mode copy of the current weights (safe to hand to another thread):
        a pooled copy nobody holds any more, refilled in place, or a new deep copy."""
        return self._copies.take()

    def predictor(self) -> DepthPredictor:
        """A predictor around a copy of the current weights (metres, as ``load_predictor``)."""
        return predictor_from_network(self.inference_network(), self.metadata, self.device, name=self.name)

    # --- training -----------------------------------------------------------------------------

    def _set_train_mode(self) -> None:
        self.net.train()
        if self.config.freeze_batchnorm:
            for m in self.net.modules():
                if isinstance(m, nn.modules.batchnorm._BatchNorm):
                    m.eval()

    def _eval_forward(self, x: torch.Tensor) -> torch.Tensor:
        was = self.net.training
        self.net.eval()
        try:
            return self.net(x)
        finally:
            if was:
                self._set_train_mode()

    def prepare(self, sample: AdaptSample) -> PreparedSample:
        return PreparedSample(sample, self._preprocessor.preprocess, self.device)

    def loss(self, batch: list[PreparedSample], rng: np.random.Generator | None = None) -> torch.Tensor:
        """Mean over the batch of the weighted self-supervised terms (``batch.batch_loss``); with
        ``rng``, the dense terms on windows of ``photometric_window`` of each side (``window.py``)."""
        log_depth = self.net(torch.cat([s.x for s in batch]))
        fraction = self.config.photometric_window
        windows = None
        if rng is not None and fraction < 1.0:
            windows = draw_windows(len(batch), tuple(log_depth.shape[-2:]), fraction, rng)
        loss = batch_loss(log_depth, batch, self.config, windows)
        if self.config.anchor_weight > 0:
            loss = loss + self.config.anchor_weight * self._anchor_term(log_depth, batch)
        return loss

    def _anchor_term(self, log_depth: torch.Tensor, batch: list[PreparedSample]) -> torch.Tensor:
        """Mean L1 of the log depth's change from the starting network, each keyframe's median
        change removed (its scale may follow the points; its shape stays where no point says)."""
        anchors = []
        for s in batch:
            if s.anchor_log is None:
                with torch.no_grad():
                    s.anchor_log = self._start_net(s.x)
            anchors.append(s.anchor_log)
        change = log_depth - torch.cat(anchors)
        shift = change.detach().flatten(1).median(dim=1).values.view(-1, 1, 1, 1)
        return (change - shift).abs().mean()

    def _guard(self, samples: list[PreparedSample]) -> list[torch.Tensor]:
        """Held-out point errors of ``samples`` that have held-out points, with the current
        weights (empty without any). Errors already computed for these weights are reused:
        after an update the next keyframe's guard runs the network on the new keyframe only."""
        usable = [s for s in samples if s.n_holdout > 0]
        missing = [s for s in usable if self._token not in s.guard_errors]
        if missing:
            for s, error in zip(missing, guard_point_errors(self._eval_forward, missing), strict=True):
                s.guard_errors[self._token] = error
        return [s.guard_errors[self._token] for s in usable]

    def _rollback(self, token: int) -> None:
        """Restore the weights and optimiser state saved before this update."""
        self._weights.restore()
        self._token = token

    def _steps(
        self, prepared: PreparedSample, abort: Callable[[], bool] | None, behind: bool = False
    ) -> list[torch.Tensor] | None:
        """``steps_per_keyframe`` optimiser steps (``steps_when_behind`` when ``behind``) on
        ``prepared`` and replayed keyframes: their losses (on the device), or None when
        ``abort`` said stop between two steps."""
        cfg = self.config
        steps = cfg.steps_when_behind if behind else cfg.steps_per_keyframe
        losses = []
        seed = [int(cfg.seed), int(self.counters.observed)]
        for step in range(steps):
            if abort is not None and abort():
                return None
            rng = np.random.default_rng([*seed, step])
            batch = [prepared, *self.buffer.draw(cfg.replay_per_step, rng)]
            loss = self.loss(batch, rng)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip > 0:
                nn.utils.clip_grad_norm_(self.net.parameters(), cfg.grad_clip)
            with COMPILE_LOCK:  # Adam's step reads torch's global compile flag (compile_lock.py)
                self.optimizer.step()
            losses.append(loss.detach())
        return losses

    def observe(
        self, sample: AdaptSample, abort: Callable[[], bool] | None = None, behind: bool = False
    ) -> UpdateReport:
        """Train on ``sample`` (+ replay); keep the update only if the guard allows it.

        ``behind``: keyframes come faster than updates (the training thread says so); the
        update takes ``steps_when_behind`` steps instead.

        ``abort`` is checked between steps (a node shutting down): a true answer restores the
        weights and reports the keyframe as skipped (``stopped``). The steps never wait for the
        device: losses stay on it until one read after the last step (a non-finite loss then
        restores the weights, as stopping at it would have).
        """
        with self._convolutions():
            return self._observe(sample, abort, behind)

    def _convolutions(self) -> contextlib.AbstractContextManager[Any]:
        """cuDNN off while training on a GPU: torch's own convolution kernels instead.

        Why: cuDNN prepares its kernels for each new batch shape once per process, and the
        guard's and the replay's batches grow with the buffer, so a training process's first
        updates took seconds each. On an H200 (2026-12-04, ``scripts/diag/adapt_update_times.py
        --cudnn``, one process each) the first five updates took 40.2 s with cuDNN, 59.2 s
        autotuned, 8.5 s without it (7.5 s of which the process's first CUDA use); later
        updates the same (median 297 / 251 ms with cuDNN, 302 / 207 ms without). The flag is
        the process's: with the training in the node's own process (``adaptation.process``
        false), inference on another thread may run without cuDNN meanwhile (the same numbers,
        to float rounding). Inference alone keeps cuDNN.
        """
        return _cudnn_disabled() if self.device.type == 'cuda' else contextlib.nullcontext()

    def _observe(self, sample: AdaptSample, abort: Callable[[], bool] | None, behind: bool) -> UpdateReport:
        t0 = time.perf_counter()
        cfg = self.config
        self.counters.observed += 1
        # These tests read the sample: a keyframe skipped is never preprocessed.
        if sample.precise_fraction < cfg.min_precise_fraction:  # NaN (no std) compares false
            reason = (
                f'imprecise_points ({sample.precise_fraction:.0%} of the points within depth_std / depth '
                f'{cfg.max_relative_std:g} < {cfg.min_precise_fraction:.0%})'
            )
            return self._skip(sample.key, reason, t0)
        if cfg.follow_fusion_guard and sample.untrusted:
            return self._skip(sample.key, f'untrusted_points ({sample.untrusted})', t0)
        n_train = len(sample.train_uv)
        if n_train < max(1, cfg.min_points):
            return self._skip(sample.key, f'too_few_points ({n_train} < {cfg.min_points})', t0)
        coverage, needed = sample.coverage(), self.coverage_needed()
        if coverage < needed:
            reason = f'too_little_coverage ({coverage:.0%} of the image < {needed:.0%})'
            return self._skip(sample.key, reason, t0)
        prepared = self.prepare(sample)
        guard_set = [prepared, *self.buffer.recent(cfg.guard_keyframes)]
        before = self._guard(guard_set)
        start = self._token
        self._weights.save()
        try:
            losses = self._steps(prepared, abort, behind)
        except BaseException:
            self._rollback(start)  # a failed step leaves no half-applied update behind
            raise
        if losses is None:
            self._rollback(start)
            return self._skip(sample.key, 'stopped', t0)
        self._token = next(self._tokens)
        values = torch.stack(losses).tolist()  # the steps' only wait for the device
        if not all(math.isfinite(v) for v in values):
            self._rollback(start)
            return self._skip(sample.key, 'non_finite_loss', t0)
        self.counters.steps += len(values)
        self.counters.behind += behind
        after = self._guard(guard_set)
        verdict = judge(before, after, cfg.guard_tolerance, cfg.guard_z)
        report = UpdateReport(
            key=sample.key,
            status='rolled_back' if verdict.rolled_back else 'updated',
            steps=len(values),
            loss_first=values[0],
            loss_last=values[-1],
            guard=verdict,
            photometric=sample.has_photometric and cfg.photometric_weight > 0,
            behind=behind,
        )
        if verdict.rolled_back:
            self._rollback(start)
            self.counters.rolled_back += 1
            log.warning(
                'adaptation: update on keyframe %d rolled back (held-out error %.4f -> %.4f, '
                'standard error %.4f, %d keyframes)',
                sample.key,
                verdict.before,
                verdict.after,
                verdict.se,
                verdict.keyframes,
            )
        else:
            self.counters.updated += 1
            self.version += 1
            self.accepted += 1
            self.buffer.add(prepared)
        for s in guard_set:  # errors of weights that are gone are never asked for again
            s.guard_errors = {t: e for t, e in s.guard_errors.items() if t == self._token}
        report.version = self.version
        report.seconds = time.perf_counter() - t0
        self.counters.train_seconds += report.seconds
        return report

    def coverage_needed(self) -> float:
        """Share of the image a keyframe's points must cover to be trained on: ``start_coverage``
        until an update was accepted, then ``min_coverage``."""
        cfg = self.config
        return cfg.min_coverage if self.accepted > 0 else max(cfg.min_coverage, cfg.start_coverage)

    @torch.no_grad()
    def restart(self, key: int, reason: str) -> UpdateReport:
        """Start over from the loaded weights: they, a fresh optimiser state and an empty replay
        buffer, as a new ``version`` (inference takes it like an update).

        Why: every keyframe trained on so far had multi-view points triangulated with poses that
        the node later found wrong (another frame's; a turn of 120 deg on 7-Scenes). A rollback
        cannot undo them: the guard judged each update on held-out points of the same wrong
        poses. Kept, those updates made the single view 0.64 m against 0.48 m with the right
        poses, live (docs/adaptation.md). ``key``: the first keyframe of the right poses.
        """
        t0 = time.perf_counter()
        start = self._start_net
        torch._foreach_copy_(
            [*self.net.parameters(), *self.net.buffers()], [*start.parameters(), *start.buffers()]
        )
        self.optimizer.state.clear()  # Adam's moments and step counts of the updates undone
        self.buffer.clear()
        self._token = next(self._tokens)  # no guard error of earlier weights is reused
        self.version += 1
        self.accepted = 0
        self.counters.restarts += 1
        log.warning('adaptation: started over from the loaded weights (version %d): %s', self.version, reason)
        return UpdateReport(key, 'restarted', reason, version=self.version, seconds=time.perf_counter() - t0)

    def _skip(self, key: int, reason: str, t0: float) -> UpdateReport:
        self.counters.skip(reason.split(' ')[0])
        log.info('adaptation: keyframe %d not trained on: %s', key, reason)
        return UpdateReport(key, 'skipped', reason, version=self.version, seconds=time.perf_counter() - t0)

    # --- persistence --------------------------------------------------------------------------

    def save(self, path: str | Path, extra_info: dict[str, Any] | None = None) -> Path:
        """Write the current weights as a checkpoint that ``model:`` / ``--single-view`` load."""
        from ..singleview.checkpoint import save_checkpoint

        info = dict(self.metadata.info)
        info['adaptation'] = {
            'adapted_from': self.name,
            'version': self.version,
            'counters': self.counters.as_dict(),
            'config': dict(self.config.__dict__),
            **(extra_info or {}),
        }
        metadata = ModelMetadata.from_dict({**self.metadata.to_dict(), 'info': info})
        return save_checkpoint(path, self.inference_network(), metadata)
