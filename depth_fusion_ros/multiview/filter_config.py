"""Parameters of the temporal inverse-depth filter (``multi_view.method: filter``).

They live apart from ``MultiViewConfig`` (the paper's sweep) so that the two methods can be
tuned independently; the matching itself (patch, blur, descriptor channels, noise floor) is
shared: the filter takes those fields from the ``MultiViewConfig`` it is given, so one
``multi_view.patch`` setting changes both methods the same way.

Defaults were chosen on the synthetic rooms (``data.synthetic``: high and low parallax,
rotation-heavy and wide-baseline motion), never on the shared real sequences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The multi-view methods: the paper's per-keyframe sweep and the temporal filter.
MULTI_VIEW_METHODS = ('sweep', 'filter')


@dataclass(frozen=True)
class FilterConfig:
    """Gaussian x uniform inverse-depth filter (Vogiatzis & Hernandez 2011; SVO, REMODE)."""

    #: Candidate pixels: the strongest this fraction of the image (gradient at least
    #: ``filter.min_gradient``). Larger than the sweep's: a filter pixel is cheap.
    max_candidate_fraction: float = 0.6
    #: Candidate pixels: grey gradient (grey in [0, 1] per px, after the matching blur) at least
    #: this. Lower than the sweep's ``multi_view.min_gradient``: a weak gradient is matched only
    #: in frames whose epipolar line crosses it (``min_epipolar_gradient``) and only published
    #: once several frames agree, so the filter can afford pixels the sweep must leave out.
    min_gradient: float = 0.01
    #: A frame searches a pixel only where the gradient along its epipolar line is at least this
    #: (LSD-SLAM): along an edge parallel to the line every position matches equally well.
    min_epipolar_gradient: float = 0.003
    #: Std of the matching error along the epipolar line (px): the measurement variance is
    #: ``(pixel_sigma / J)^2`` with ``J`` the epipolar motion per unit inverse depth.
    pixel_sigma: float = 1.0
    #: Pose noise (m) of the camera positions: a relative std ``pose_sigma / baseline`` of the
    #: measured inverse depth, added to ``tau^2``. Frames close to the keyframe then weigh
    #: little however sharp their match (a 2 mm pose error over a 5 mm baseline is a 40 %
    #: depth error). Default 0: the defaults are chosen on synthetic sequences, whose poses
    #: are exact; set it to the pose source's noise.
    pose_sigma: float = 0.0
    #: A pixel with an estimate is searched in a frame only when the frame can still teach it
    #: something: prior variance / predicted measurement variance at least this (REMODE stops
    #: updating converged seeds). Saves searches once estimates have converged.
    min_information: float = 0.1
    #: Search interval: the prior mean +- ``search_sigmas`` standard deviations (at least
    #: ``min_search_px``).
    search_sigmas: float = 2.0
    #: The search interval spans at least +- this many pixels along the epipolar line: a
    #: converged estimate is still checked, so a wrong one can fail (2 before 2026-11-23:
    #: +-1.25 px at the same sample spacing is as accurate on the synthetic rooms, 25 % cheaper).
    min_search_px: float = 1.25
    #: Samples of a short search (a pixel with an estimate; the parabola goes through them).
    short_samples: int = 8
    #: Samples of a long search (a pixel without an estimate: the whole inverse-depth range).
    long_samples: int = 32
    #: A search is short when its interval spans at most this many pixels per sample.
    max_step_px: float = 1.0
    #: Samples of a search whose interval spans at most ``(verify_samples - 1) x max_step_px``
    #: px: a converged estimate at the ``min_search_px`` floor, whose search checks that the
    #: patch is still where the estimate says (0 = off: ``short_samples``).
    verify_samples: int = 6
    #: Samples of a search (whole-range or wide prior) whose interval spans at most
    #: ``(medium_samples - 1) x max_step_px`` px: already about a pixel apart, so no refinement
    #: (0 = off: ``long_samples`` and the refinement).
    medium_samples: int = 16
    #: Fine samples on each side of the best coarse sample of a long search.
    refine_samples: int = 2
    #: Long searches a pixel without an estimate gets per keyframe (texture-less pixels never match).
    seed_attempts: int = 2
    #: The first search of a pixel without an estimate spans the inverse depths of the measured
    #: pixels within this radius (px; widened by ``2 min_search_px`` px each side) instead of the
    #: whole range; the second, if it fails, the whole range. 0 = always the whole range.
    seed_radius: int = 3
    #: A pixel without an estimate is searched over the whole range only in frames with at least
    #: this baseline / scene depth: from a short baseline the whole range spans a few pixels,
    #: and a wrong first measurement is then confirmed by the short searches around it.
    seed_parallax: float = 0.03
    #: A first measurement (a birth, a filled hole, an estimate carried across a jump) is searched
    #: again over +- this many pixels around its match, one sample a pixel, and counts only when
    #: no other minimum there comes within ``first_check_distinctiveness`` of it: on a texture
    #: that repeats along the line every few pixels, the first match (from a whole-range search's
    #: coarse samples, or a neighbours' prior) is a neighbouring period as often as not, and the
    #: later short searches confirm it (``filter_first_check``). 0: off
    first_check_px: float = 10.0
    #: The distinctiveness (``1 - c1 / c2``, as ``min_distinctiveness``) a first measurement
    #: needs within ``first_check_px``
    first_check_distinctiveness: float = 0.2
    #: A match whose cost (1 - ZNCC) is above this is a failed observation (an outlier vote).
    max_cost: float = 0.4
    #: New pixels (long search) need a distinct minimum: modified second-best ratio at least this.
    min_distinctiveness: float = 0.1
    #: A search whose best sample lies at either end of its interval measured nothing: the
    #: minimum is outside. A pixel with an estimate takes it as an outlier vote (its prior is
    #: off, or the patch is gone), a new pixel is not born from it. Off: the parabola is
    #: clamped to the end sample and counted as a measurement (before 2026-11-27), which let a
    #: wrong estimate confirm itself at its interval's edge frame after frame.
    reject_edge_minima: bool = True
    #: Beta prior ``a`` of a new pixel's inlier ratio (10 as SVO).
    init_a: float = 10.0
    #: Beta prior ``b`` of a new pixel's inlier ratio (10 as SVO).
    init_b: float = 10.0
    #: Estimates are dropped (reset to no estimate) when the inlier ratio ``a / (a + b)`` falls below this.
    min_inlier_ratio: float = 0.3
    #: Estimates are published only with an inlier ratio at least this.
    publish_inlier_ratio: float = 0.5
    #: Estimates are published only after at least this many measurements.
    min_updates: int = 2
    #: In the stream's first keyframe (nothing carried into it) an estimate is published only
    #: after at least this many measurements (the larger of this and ``min_updates``). There
    #: every estimate was born from one seed search and confirmed by short searches bounded by
    #: that seed, and the first frames with enough parallax measure all of them at once, so
    #: they can be wrong together: a causal stream's first published keyframe was 21 % too
    #: near on 7-Scenes (every estimate at 2 measurements; fused 1.59x its single-view MAE),
    #: and 1.12-1.33x on rotation stress seeds 1-3 at 320x240. Later keyframes carry
    #: estimates with their history and keep ``min_updates`` (docs/multi_view.md, "A stream's
    #: first keyframe"). ``min_updates`` or less: off.
    first_keyframe_min_updates: int = 3
    #: Stage-1 ranking: ``score = inlier_ratio * (mu / sigma) ** this`` (the posterior's relative
    #: precision). 0: the inlier ratio alone (the relative precision also says how long a
    #: region has been observed, and can pack the stage-1 points into it).
    score_relative_power: float = 0.0
    #: Published only when the inverse-depth std is at most this fraction of the inverse depth.
    max_relative_sigma: float = 0.1
    #: Nothing is published while fewer than this share of the measured estimates (``min_updates``
    #: measurements, ``publish_inlier_ratio``) pass ``max_relative_sigma``. The test divides by
    #: the estimate's own ``mu``, so an estimate its noise made too near passes it sooner: where
    #: the parallax lets only a minority pass, that minority is the noise-selected tail
    #: (rotation stress case, 160x120, 7 frames: all measured estimates 1-3 % too near in the
    #: median, the published ones 5-69 % too near where 1 % or less passed and up to 2x too
    #: near, the front surface's depth carried across its outline, where 9-10 % passed).
    #: Rotation-heavy keyframes pass 0.1-23 % at 160x120 and 23-84 % at 320x240; every
    #: keyframe with translation, synthetic or real, 47 % or more. 0.2 (0.05 until
    #: 2026-11-27 afternoon) keeps every stress case, seeds 0-29, at or below its single-view
    #: MAE (docs/multi_view.md, "A minority is not evidence"). 0: off.
    min_published_fraction: float = 0.2
    #: The same test per region: the image is cut into this many cells across (rows in
    #: proportion, square cells), and in a cell where fewer than ``min_published_fraction`` of
    #: the measured estimates pass, none of them is published. The keyframe-wide share hides a
    #: far region whose passing few are its noise-selected tail when a near region passes
    #: whole: on a live 600-frame synthetic room (320x240) the first published keyframe had
    #: 3854 measured estimates in the far wall's top-left 80 px square, 40 passed and all 40
    #: were 2-4x too near (46 % passed over the keyframe), and the fusion bent the wall to 0.6x
    #: (fused 2.1x its single-view MAE; docs/multi_view.md, "A minority is not evidence, per
    #: region"). 0: off (the keyframe-wide test alone).
    published_fraction_cells: int = 8
    #: A frame updates the keyframe only with baseline / scene depth at least this (below: skipped).
    min_parallax: float = 0.003
    #: A frame updates the keyframe only with a rotation to it of at most this (degrees).
    max_rotation_deg: float = 25.0
    #: A frame becomes the new filter keyframe at this baseline / scene depth ...
    keyframe_parallax: float = 0.12
    #: ... or at this rotation to the keyframe (degrees) ...
    keyframe_rotation_deg: float = 20.0
    #: ... or when less than this fraction of the estimates projects into it.
    keyframe_min_visible: float = 0.6
    #: Propagation into a new keyframe multiplies the variance by this.
    propagation_inflation: float = 1.5
    #: Propagation into a new keyframe adds this std relative to the inverse depth.
    propagation_relative_sigma: float = 0.01
    #: New keyframe pixels between carried estimates get a prior from those within this radius
    #: (px; LSD-SLAM's hole filling): a short search instead of a whole-range one. 0 = off.
    fill_radius: int = 2
    #: ... when at least this many carried estimates lie within the radius.
    fill_min_neighbours: int = 3
    #: Only carried estimates with at least this many measurements fill holes (1: every carried
    #: one, before 2026-11-29). A young estimate may be wrong, and a prior filled from it is
    #: confirmed by the short searches around it: on a keyframe stream, where the keyframe
    #: changes every frame, 11-27 % of the estimates published were more than 10 % off (mostly
    #: too near) with 1, 6-11 % with 3; the synthetic room's good density is unchanged
    #: (docs/multi_view.md, "Young estimates on a keyframe stream").
    fill_min_updates: int = 3
    #: Scene depth (m) assumed before any estimate exists (parallax of the first frames).
    scene_depth: float = 1.5
    #: How far camera_info's focal length may be off (relative) until the focal length check
    #: has verified it, and while the check cannot tell: the published depth std then includes
    #: the bias such an error gives each estimate under this motion (``multiview/focal_bias.py``:
    #: large under rotation-dominant motion, small with a sideways baseline). Once the check has
    #: read the stream, its standard error is used instead. 0: off.
    focal_uncertainty: float = 0.1
    #: Refine each frame's pose against the filter keyframe's image before it updates the filter:
    #: corners tracked into the frame, the pose that puts them on their epipolar lines under a
    #: prior at the told pose (``multiview/pose_refinement.py``). A SLAM's or a motion capture's
    #: poses carry noise the images can see; with exact poses (a simulator) it costs a little.
    refine_poses: bool = True
    #: The refinement's prior: std of the told pose's rotation (degrees). The epipolar
    #: constraint cannot tell a short baseline's turn from a sideways step; the prior decides.
    #: The tracks fix a pose's turn far better than this wherever they can; where they cannot,
    #: a loose prior let an unmodelled lens distortion turn rotation sweeps by 1.5 deg
    #: (0.5 deg: 59 % of the estimates wrong against 22 % with the told poses; 0.15: 28 %).
    refine_sigma_deg: float = 0.15
    #: The refinement's prior: std of the told pose's camera centre (m). The images do not tell
    #: the baseline's length; the prior holds it.
    refine_sigma_m: float = 0.01
    #: Corners of the keyframe tracked into each frame for the refinement, at most.
    refine_corners: int = 300

    def seeds_at(self, parallax: float) -> bool:
        """Whether a frame at ``parallax`` (baseline / scene depth) searches pixels without an
        estimate over the whole range (``seed_parallax``)."""
        return parallax >= self.seed_parallax

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad ``filter.<parameter>``."""
        checks = (
            ('max_candidate_fraction', 0 < self.max_candidate_fraction <= 1, 'in (0, 1]'),
            ('min_gradient', self.min_gradient >= 0, '>= 0'),
            ('min_epipolar_gradient', self.min_epipolar_gradient >= 0, '>= 0'),
            ('pixel_sigma', self.pixel_sigma > 0, 'positive'),
            ('pose_sigma', self.pose_sigma >= 0 and math.isfinite(self.pose_sigma), '>= 0'),
            ('min_information', self.min_information >= 0, '>= 0'),
            ('search_sigmas', self.search_sigmas > 0, 'positive'),
            ('min_search_px', self.min_search_px > 0, 'positive'),
            ('short_samples', self.short_samples >= 3, '>= 3'),
            ('long_samples', self.long_samples >= 3, '>= 3'),
            ('max_step_px', self.max_step_px > 0, 'positive'),
            (
                'verify_samples',
                self.verify_samples == 0 or 3 <= self.verify_samples <= self.short_samples,
                '0 or in [3, filter.short_samples]',
            ),
            (
                'medium_samples',
                self.medium_samples == 0 or self.short_samples < self.medium_samples <= self.long_samples,
                '0 or in (filter.short_samples, filter.long_samples]',
            ),
            ('seed_radius', self.seed_radius >= 0, '>= 0'),
            ('refine_samples', self.refine_samples >= 1, '>= 1'),
            ('seed_parallax', self.seed_parallax >= 0, '>= 0'),
            ('seed_attempts', self.seed_attempts >= 1, '>= 1'),
            ('first_check_px', 0 <= self.first_check_px <= 100, 'in [0, 100]'),
            ('first_check_distinctiveness', 0 <= self.first_check_distinctiveness <= 1, 'in [0, 1]'),
            ('max_cost', 0 < self.max_cost <= 2, 'in (0, 2]'),
            ('init_a', self.init_a > 0, 'positive'),
            ('init_b', self.init_b > 0, 'positive'),
            ('min_inlier_ratio', 0 <= self.min_inlier_ratio < 1, 'in [0, 1)'),
            ('publish_inlier_ratio', 0 <= self.publish_inlier_ratio <= 1, 'in [0, 1]'),
            ('min_updates', self.min_updates >= 1, '>= 1'),
            ('first_keyframe_min_updates', self.first_keyframe_min_updates >= 1, '>= 1'),
            ('score_relative_power', self.score_relative_power >= 0, '>= 0'),
            ('max_relative_sigma', self.max_relative_sigma > 0, 'positive'),
            ('min_published_fraction', 0 <= self.min_published_fraction <= 1, 'in [0, 1]'),
            ('published_fraction_cells', self.published_fraction_cells >= 0, '>= 0'),
            ('min_parallax', self.min_parallax >= 0, '>= 0'),
            ('keyframe_parallax', self.keyframe_parallax > self.min_parallax, '> filter.min_parallax'),
            ('keyframe_min_visible', 0 <= self.keyframe_min_visible <= 1, 'in [0, 1]'),
            ('propagation_inflation', self.propagation_inflation >= 1, '>= 1'),
            ('propagation_relative_sigma', self.propagation_relative_sigma >= 0, '>= 0'),
            ('fill_radius', self.fill_radius >= 0, '>= 0'),
            ('fill_min_neighbours', self.fill_min_neighbours >= 1, '>= 1'),
            ('fill_min_updates', self.fill_min_updates >= 1, '>= 1'),
            ('scene_depth', self.scene_depth > 0 and math.isfinite(self.scene_depth), 'positive'),
            ('focal_uncertainty', 0 <= self.focal_uncertainty <= 1, 'in [0, 1]'),
            ('refine_sigma_deg', 0 < self.refine_sigma_deg <= 45, 'in (0, 45]'),
            ('refine_sigma_m', 0 < self.refine_sigma_m <= 10, 'in (0, 10]'),
            ('refine_corners', 20 <= self.refine_corners <= 10000, 'in [20, 10000]'),
        )
        for name, ok, what in checks:
            if not ok:
                raise ValueError(f'filter.{name} must be {what}, got {getattr(self, name)}')
        for name in ('max_rotation_deg', 'keyframe_rotation_deg'):
            if not (0 < getattr(self, name) <= 180):
                raise ValueError(f'filter.{name} must be in (0, 180], got {getattr(self, name)}')
