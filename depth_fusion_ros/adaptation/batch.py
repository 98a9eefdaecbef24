"""One training step's batch: the prepared keyframes' tensors stacked, and its loss.

Each keyframe of a step (the new one and the replayed ones) contributes the same terms as
before (``losses.py``), but they are evaluated for the whole batch at once: one sparse
sampling for all keyframes' points (padded to the longest), one warp and one SSIM pass for
every (keyframe, neighbour) pair, one smoothness pass. On a GPU that is a few dozen kernels
per step instead of a few hundred, and nothing here waits for the device: empty masks give a
zero term by arithmetic, not by a host-side test. The depth-independent tensors come from
each keyframe's cache (``prepared.py``); stacking them is the only per-step preparation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import torch

from .config import AdaptConfig
from .losses import KeyStats, PhotometricBatch, photometric_batch, smoothness_batch, sparse_batch
from .prepared import GridTensors, PhotometricTensors, PreparedSample
from .window import Window, cut


@dataclass
class PointBatch:
    """Points of every keyframe, padded to the longest: what :func:`~.losses.sparse_batch` takes."""

    grid: torch.Tensor  # (B, M, 2)
    target: torch.Tensor  # (B, M)
    mask: torch.Tensor  # (B, M) bool


def point_batch(grids: Sequence[torch.Tensor], targets: Sequence[torch.Tensor]) -> PointBatch:
    """Stack per-keyframe (N_b, 2) grids and (N_b,) targets into a padded :class:`PointBatch`."""
    longest = max(1, *(int(g.shape[0]) for g in grids))  # a zero-size grid_sample is refused
    ref = grids[0]
    grid = ref.new_zeros((len(grids), longest, 2))
    target = ref.new_zeros((len(grids), longest))
    mask = torch.zeros((len(grids), longest), dtype=torch.bool, device=ref.device)
    for b, (g, t) in enumerate(zip(grids, targets, strict=True)):
        n = int(g.shape[0])
        grid[b, :n] = g
        target[b, :n] = t
        mask[b, :n] = True
    return PointBatch(grid, target, mask)


def photometric_pairs(photos: Sequence[PhotometricTensors | None]):
    """The :class:`~.losses.PhotometricBatch` of a batch's keyframes (their photometric tensors
    on the loss grid, or a window of it), or None when none of them has posed neighbours."""
    counts = [0 if p is None else int(p.neighbours.shape[0]) for p in photos]
    pairs = sum(counts)
    if pairs == 0:
        return None
    used = [p for p in photos if p is not None]
    owner, slots = _pair_index(tuple(counts), used[0].neighbours.device)

    def per_pair(get) -> torch.Tensor:
        return torch.cat([get(p).expand(p.neighbours.shape[0], *get(p).shape[1:]) for p in used])

    stats = KeyStats(
        image=per_pair(lambda p: p.stats.image),
        mu=per_pair(lambda p: p.stats.mu),
        mu_sq=per_pair(lambda p: p.stats.mu_sq),
        sigma=per_pair(lambda p: p.stats.sigma),
    )
    shared = all(p.rays_key == used[0].rays_key for p in used[1:])
    return PhotometricBatch(
        neighbours=torch.cat([p.neighbours for p in used]),
        stats=stats,
        identity=torch.cat([p.identity for p in used]),
        rays=used[0].rays if shared else per_pair(lambda p: p.rays[None]),
        k=used[0].k if shared else per_pair(lambda p: p.k[None]),
        t_ok=torch.cat([p.t_ok for p in used]),
        owner=owner,
        slots=slots,
    )


@lru_cache(maxsize=64)
def _pair_index(counts: tuple[int, ...], device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``owner`` (P,) and ``slots`` (B, M) of :class:`~.losses.PhotometricBatch` for keyframes
    with ``counts`` neighbours each, on ``device`` (cached: a blocking host-to-device copy
    per step would make the host wait for the device)."""
    pairs = sum(counts)
    owner = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    slots = torch.full((len(counts), max(counts)), pairs, dtype=torch.long)
    start = 0
    for b, n in enumerate(counts):
        slots[b, :n] = torch.arange(start, start + n)
        start += n
    return owner.to(device), slots.to(device)


def batch_loss(
    log_depth: torch.Tensor,
    samples: Sequence[PreparedSample],
    config: AdaptConfig,
    windows: Sequence[Window] | None = None,
) -> torch.Tensor:
    """Mean over the batch of the weighted self-supervised terms of each keyframe, for the
    network's output ``log_depth`` (B, 1, h, w) on ``samples`` (in that order).

    ``windows`` (one per keyframe, ``window.py``): the photometric and smoothness terms are
    computed on those windows of the output only; the sparse term reads every point.
    """
    h, w = log_depth.shape[-2:]
    points = point_batch([s.train_grid for s in samples], [s.train_log for s in samples])
    per_keyframe = config.sparse_weight * sparse_batch(log_depth, points.grid, points.target, points.mask)
    if config.photometric_weight <= 0 and config.smoothness_weight <= 0:
        return per_keyframe.sum() / len(samples)
    grids: list[GridTensors] = [s.grid(h, w, config.ssim_alpha) for s in samples]
    if windows is not None:
        grids = [win.grid(g) for win, g in zip(windows, grids, strict=True)]
        log_depth = cut(log_depth, windows)
    if config.photometric_weight > 0:
        pairs = photometric_pairs([g.photometric for g in grids])
        if pairs is not None:
            per_keyframe = per_keyframe + config.photometric_weight * photometric_batch(
                log_depth, pairs, config.ssim_alpha
            )
    if config.smoothness_weight > 0:
        wx = torch.cat([g.weight_x for g in grids])
        wy = torch.cat([g.weight_y for g in grids])
        per_keyframe = per_keyframe + config.smoothness_weight * smoothness_batch(log_depth, wx, wy)
    return per_keyframe.sum() / len(samples)
