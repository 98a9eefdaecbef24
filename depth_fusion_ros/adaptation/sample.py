"""One keyframe's training signals, built only from what the graph publishes.

An :class:`AdaptSample` holds the keyframe image, the selected multi-view points split into
training and held-out ones (the guard's), and, when poses are known, the keyframe pose and
posed neighbour images for the photometric term. Nothing here ever reads ground truth: the
split and the selection use the multi-view depth and its score only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import PinholeCamera
from ..fusion.guard import relative_std, within_relative_std
from ..image_cells import ImageCells
from ..multiview.stage1 import best_fraction_mask


@dataclass
class Neighbour:
    """A posed view of the scene used to check the keyframe's depth photometrically."""

    rgb: np.ndarray
    #: Camera-to-world pose (4x4).
    pose: np.ndarray


@dataclass
class AdaptSample:
    """Training signals of one keyframe (working grid, undistorted)."""

    key: int
    rgb: np.ndarray
    camera: PinholeCamera
    #: (N, 2) pixel coordinates (u = column, v = row) and (N,) depths (m) of the training points.
    train_uv: np.ndarray
    train_depth: np.ndarray
    #: The same for the held-out points (guard only, never trained on).
    holdout_uv: np.ndarray
    holdout_depth: np.ndarray
    #: Camera-to-world pose of the keyframe, or None (then no photometric term).
    pose: np.ndarray | None = None
    neighbours: list[Neighbour] = field(default_factory=list)
    #: Share of the selected points whose ``depth_std / depth`` is within the limit
    #: (``fusion.guard.within_relative_std``); NaN when the multi-view std did not come.
    precise_fraction: float = float('nan')
    #: Why the fusion's guard trusted none of the points ('' when it did, or said nothing):
    #: ``fusion_trust.untrusted_reason``.
    untrusted: str = ''

    @property
    def has_photometric(self) -> bool:
        return self.pose is not None and len(self.neighbours) > 0

    def coverage(self) -> float:
        """Share of the image's cells (:data:`COVERAGE_CELLS_ACROSS`) holding enough training points
        (:func:`point_coverage`): how much of the view the points speak for."""
        return point_coverage(self.train_uv, self.rgb.shape[:2])


#: Cells across the image that :meth:`AdaptSample.coverage` counts (square cells, rows in
#: proportion: 8 x 6 at 4:3, 40 px at 320x240; ``image_cells.ImageCells``).
COVERAGE_CELLS_ACROSS = 8
#: Training points a cell needs to count as covered: 5, or a fifth of the points a cell would
#: hold if they were spread evenly where there are fewer (a small working grid), at least 1.
COVERAGE_MIN_POINTS = 5
COVERAGE_MIN_SHARE = 0.2


def point_coverage(uv: np.ndarray, shape: tuple[int, int]) -> float:
    """Share of the :data:`COVERAGE_CELLS_ACROSS` cells over an image of ``shape`` (rows,
    columns) holding enough of the points ``uv`` ((N, 2) columns, rows):
    :data:`COVERAGE_MIN_POINTS`, or :data:`COVERAGE_MIN_SHARE` of an even spread when that is
    fewer, at least one."""
    if len(uv) == 0:
        return 0.0
    height, width = shape
    cells = ImageCells.across(width, height, COVERAGE_CELLS_ACROSS)
    counts = np.bincount(cells.index(uv[:, 0], uv[:, 1]), minlength=cells.count)
    needed = min(COVERAGE_MIN_POINTS, max(1.0, COVERAGE_MIN_SHARE * len(uv) / cells.count))
    return float(np.count_nonzero(counts >= needed)) / cells.count


def split_holdout(count: int, fraction: float, seed: tuple[int, ...]) -> np.ndarray:
    """Bool mask of the ``count`` points that are held out (a seeded draw, ``fraction`` of them)."""
    rng = np.random.default_rng(list(seed))
    held = np.zeros(count, dtype=bool)
    n_held = round(fraction * count)
    if n_held:
        held[rng.choice(count, size=n_held, replace=False)] = True
    return held


def make_sample(
    key: int,
    rgb: np.ndarray,
    camera: PinholeCamera,
    mv_depth: np.ndarray,
    mv_score: np.ndarray,
    *,
    select_fraction: float = 0.25,
    holdout_fraction: float = 0.2,
    seed: int = 0,
    pose: np.ndarray | None = None,
    neighbours: list[Neighbour] | None = None,
    mv_std: np.ndarray | None = None,
    max_relative_std: float = 0.15,
    untrusted: str = '',
    points_scale: float = 1.0,
) -> AdaptSample:
    """A sample from a keyframe's multi-view depth and score maps (NaN = no estimate).

    Stage 1 keeps the best ``select_fraction`` by score (as the fusion does); of those, a seeded
    ``holdout_fraction`` is kept apart for the guard. ``mv_std`` (the depth's std, optional)
    gives the share of them precise at ``max_relative_std``. ``untrusted``: the fusion's reason
    for trusting none of them (``fusion_trust.untrusted_reason``), '' otherwise.
    ``points_scale``: the factor the fusion moved the points by (``fusion_trust.points_scale``:
    the share of their global scale a bias they all share left them); the targets, held-out
    ones included, are the points so moved.
    """
    if mv_depth.shape != rgb.shape[:2] or mv_score.shape != rgb.shape[:2]:
        raise ValueError(
            f'multi-view depth {mv_depth.shape} / score {mv_score.shape} differ from image {rgb.shape[:2]}'
        )
    with np.errstate(invalid='ignore'):
        depth = np.where(mv_depth > 0, mv_depth, np.nan).astype(np.float32)
    mask = best_fraction_mask(depth, mv_score, select_fraction)
    rows, cols = np.nonzero(mask)
    uv = np.stack([cols, rows], axis=1).astype(np.float32)
    values = depth[rows, cols].astype(np.float32)
    share = float('nan')
    if mv_std is not None and len(values):
        # A share too small to be evidence skips the keyframe (Adapter.observe). The points stay
        # targets otherwise: keeping only the precise ones made the SLAM keyframe streams'
        # adapted network 1.2-1.4x worse (their far points left; docs/adaptation.md).
        precise = within_relative_std(relative_std(values, mv_std[rows, cols]), max_relative_std)
        share = float(precise.mean())
    if points_scale != 1.0:
        values = (values * np.float32(points_scale)).astype(np.float32)
    held = split_holdout(len(values), holdout_fraction, (int(seed), int(key) & 0x7FFFFFFF))
    return AdaptSample(
        key=int(key),
        rgb=rgb,
        camera=camera,
        train_uv=uv[~held],
        train_depth=values[~held],
        holdout_uv=uv[held],
        holdout_depth=values[held],
        pose=None if pose is None else np.asarray(pose, dtype=np.float64),
        neighbours=list(neighbours or []) if pose is not None else [],
        precise_fraction=share,
        untrusted=untrusted,
    )
