"""Settings of the online adaptation (the ``adaptation.*`` parameters of ``single_view_node``).

Defaults were chosen on synthetic sequences (``depth-fusion synth``), never on the shared
real data: see docs/adaptation.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any


@dataclass
class AdaptConfig:
    """How the network learns from each keyframe."""

    #: Adam learning rate of the network's weights.
    lr: float = 3e-4
    #: Learning rate of the output bias (a global log-depth offset): the scale of a network
    #: trained elsewhere is its largest error and must move within a few keyframes.
    scale_lr: float = 2e-2
    #: Optimiser steps per keyframe (each on the keyframe plus replayed ones).
    steps_per_keyframe: int = 6
    #: Past keyframes kept for replay (oldest replaced first).
    buffer_size: int = 32
    #: Replayed keyframes in each step's batch, besides the new keyframe.
    replay_per_step: int = 2
    #: Optimiser steps of an update made while training is behind: the training thread found
    #: another keyframe waiting, keyframes were dropped since it took its last one, or its last
    #: update took longer than keyframes come (a live node on a small CPU); and its first
    #: update. The same CPU then reaches more keyframes with fewer steps each
    #: (docs/adaptation.md, "On a CPU budget"). Offline (``evaluate``, ``depth-fusion adapt``)
    #: training is never behind.
    steps_when_behind: int = 2
    #: The photometric and smoothness terms of a training step are computed on a window of
    #: this fraction of each keyframe's height and width (drawn anew for every keyframe of
    #: every step; the network still sees whole keyframes and the sparse term every point):
    #: a quarter of the loss's pixels at 0.5, a step about 30 % cheaper on a CPU, so a starved
    #: training thread reaches more keyframes (docs/adaptation.md, "Windows"). 1 = whole.
    photometric_window: float = 0.5
    #: Weight of the sparse term: L1 of log depth at the selected multi-view points.
    sparse_weight: float = 1.0
    #: Weight of the photometric term (SSIM + L1 against the posed neighbours); 0 disables it.
    photometric_weight: float = 1.0
    #: Weight of the edge-aware smoothness of mean-normalised inverse depth.
    smoothness_weight: float = 1e-3
    #: Weight of the anchor: L1 of the log depth's change from the network it started from,
    #: each keyframe's median change (its scale) allowed (docs/adaptation.md "The anchor").
    anchor_weight: float = 0.5
    #: SSIM share of the photometric error (the rest is L1), as Monodepth2.
    ssim_alpha: float = 0.85
    #: Stage-1 selection: the best fraction of the multi-view points by score are targets.
    select_fraction: float = 0.25
    #: Share of the selected points held out of training for the guard.
    holdout_fraction: float = 0.2
    #: A keyframe with fewer training points than this is not trained on (counted as skipped).
    min_points: int = 30
    #: A keyframe whose training points cover less than this share of the image (square cells,
    #: 8 across (8 x 6 at 4:3), holding at least 5 points, fewer for a sparse set:
    #: ``sample.point_coverage``)
    #: is not trained on (skipped, too_little_coverage). 0: any coverage.
    min_coverage: float = 0.25
    #: The same, until the first update is accepted: the first updates set the network's scale
    #: for the whole view. A live filter's first points lie on the few surfaces that converge
    #: first, where a network trained elsewhere can be far more wrong than over the view (1.8x
    #: against 0.9x on a synthetic room), and one update on them moved the whole depth by 30-40 %
    #: (docs/adaptation.md, "The first keyframes").
    start_coverage: float = 0.5
    #: A selected point is precise when its ``depth_std / depth`` (the multi-view node's std: one
    #: pixel of matching error and the filter's focal length bias) is at most this, as the
    #: fusion's ``guard.max_relative_std``.
    max_relative_std: float = 0.15
    #: A keyframe whose selected points are precise in a smaller share is not trained on (skipped,
    #: imprecise_points), as the fusion's guard trusts none of them then: a focal length the
    #: check could not verify under rotation biases them all (docs/adaptation.md, "Points the
    #: fusion does not trust"). 0: every keyframe.
    min_precise_fraction: float = 0.2
    #: A keyframe whose points the fusion's guard trusted none of (its verdict ``single_view``,
    #: or withheld) is not trained on (skipped, untrusted_points): points wrong together pass
    #: the adaptation's own tests, which judge them on points of the same kind
    #: (adaptation/fusion_trust.py; docs/adaptation.md, "Keyframes the guard did not trust").
    #: Without a fusion (no verdict ever heard) nothing changes.
    follow_fusion_guard: bool = True
    #: Recent replay keyframes whose held-out points the guard checks with the new keyframe's.
    guard_keyframes: int = 4
    #: An update is rolled back when the guard error grows by more than this fraction (and
    #: the held-out points show it, see guard_z).
    guard_tolerance: float = 0.02
    #: Standard errors (of the paired per-point before/after change) by which the growth must
    #: exceed guard_tolerance to roll back: a one-sided test, 2.33 = 1 % false rollbacks;
    #: 0 = the bare threshold.
    guard_z: float = 2.33
    #: Gradient norm clipping (0: none).
    grad_clip: float = 1.0
    #: Keep BatchNorm statistics frozen (eval-mode normalisation while training).
    freeze_batchnorm: bool = True
    #: Seed of the replay choices and the held-out split.
    seed: int = 0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field."""
        positive = ('lr', 'steps_per_keyframe', 'steps_when_behind', 'buffer_size')
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f'adaptation.{name} must be positive, got {getattr(self, name)}')
        nonneg = (
            'scale_lr',
            'replay_per_step',
            'sparse_weight',
            'photometric_weight',
            'smoothness_weight',
            'anchor_weight',
            'guard_keyframes',
            'guard_tolerance',
            'guard_z',
            'grad_clip',
            'min_points',
        )
        for name in nonneg:
            if getattr(self, name) < 0:
                raise ValueError(f'adaptation.{name} must be >= 0, got {getattr(self, name)}')
        if not self.max_relative_std > 0:
            raise ValueError(f'adaptation.max_relative_std must be positive, got {self.max_relative_std}')
        for name in ('min_coverage', 'start_coverage', 'min_precise_fraction'):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f'adaptation.{name} must be in [0, 1], got {getattr(self, name)}')
        for name in ('select_fraction',):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f'adaptation.{name} must be in (0, 1], got {getattr(self, name)}')
        if not 0 <= self.holdout_fraction < 1:
            raise ValueError(f'adaptation.holdout_fraction must be in [0, 1), got {self.holdout_fraction}')
        if not 0 < self.photometric_window <= 1:
            raise ValueError(
                f'adaptation.photometric_window must be in (0, 1], got {self.photometric_window}'
            )
        if not 0 <= self.ssim_alpha <= 1:
            raise ValueError(f'adaptation.ssim_alpha must be in [0, 1], got {self.ssim_alpha}')

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AdaptConfig:
        """A config from ``{field: value}`` (unknown fields are an error naming them)."""
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ValueError(f'unknown adaptation parameter(s) {unknown}; known: {sorted(known)}')
        values = {}
        for name, value in data.items():
            kind = type(known[name].default)
            values[name] = kind(value) if kind is not bool else bool(value)
        cfg = cls(**values)
        cfg.validate()
        return cfg
