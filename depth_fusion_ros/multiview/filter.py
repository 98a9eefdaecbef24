"""Temporal inverse-depth filter: every posed frame refines the current keyframe's depth.

``multi_view.method: filter`` (the paper's per-keyframe sweep stays as ``sweep``). Anchors:
LSD-SLAM's semi-dense depth filter (keyframe propagation, variance from the geometry) and
SVO / REMODE's Gaussian x uniform seeds (``filter_update``). Per pixel of the filter's
keyframe (the strongest ``filter.max_candidate_fraction`` gradients): inverse depth ``mu``,
variance ``var``, Beta ``a``, ``b`` (inlier ratio ``a / (a + b)``) and a measurement count.

For each posed frame, in stream order (:meth:`DepthFilter.process`):

1. **Skip** it if its baseline / scene depth is below ``min_parallax`` (no depth information,
   and a frame too close to the keyframe adds correlated noise) or it turned more than
   ``max_rotation_deg`` (the patch no longer keeps its shape).
2. **Update**: cheap tests on every pixel pick those the frame can teach something: the
   gradient along the epipolar line at least ``min_epipolar_gradient`` (LSD-SLAM), the prior
   variance at least ``min_information`` x the frame's measurement variance (REMODE), a
   whole-range search only from frames with ``seed_parallax`` and ``seed_attempts`` left.
   Those are searched along their epipolar line within ``mu +- search_sigmas sigma`` (at
   least +-``min_search_px``; the neighbours' range or the whole range for a pixel without a
   prior), ``filter_search``; the match
   gives a measurement ``x`` with variance ``tau^2 = (pixel_sigma / J)^2`` (+ the pose noise
   term), ``J`` the epipolar motion per unit inverse depth (one pixel of matching error
   back-propagated, as the sweep's geometric score). Then the Gaussian x uniform update; a
   visible pixel that matched nothing gets an outlier vote; a pixel whose inlier ratio drops
   below ``min_inlier_ratio`` is reset to "no estimate".
3. **New keyframe** when the parallax reaches ``keyframe_parallax``, the rotation
   ``keyframe_rotation_deg`` or the visible fraction of the estimates falls below
   ``keyframe_min_visible``: the estimates are propagated into the frame
   (``filter_propagate``: warped mean, inflated variance, Beta carried), holes between
   carried estimates get their neighbours' mean as a prior (LSD-SLAM), and every pixel left
   without a carried estimate gets its first measurement from the previous keyframe image.

:meth:`DepthFilter.result` publishes the keyframe's converged estimates, or warps them into
any other posed frame (the keyframe of the node or of the evaluation need not be the
filter's own keyframe). Everything is torch on ``device``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from ..camera import PinholeCamera
from ..chunking import effective_chunk_elements
from ..geometry import relative_pose, rotation_angle, validate_pose
from .descriptors import gaussian_blur, patch_reach, stage_descriptors
from .filter_config import FilterConfig
from .filter_geometry import FrameGeometry, frame_geometry, grid_rows_in_place, row_motion
from .filter_keyframe import FilterKeyframe
from .filter_profile import StageClock
from .filter_propagate import warp_estimates
from .filter_result import FilterResult, assemble_result
from .filter_search import plan_buckets, search_buckets, search_interval
from .filter_update import BetaGaussian, gaussian_uniform_update, outlier_vote
from .filter_window import box_sum, window_reduce
from .semidense import MultiViewConfig, candidate_mask
from .views import _as_gray

log = logging.getLogger(__name__)

#: What :meth:`DepthFilter.process` did with a frame.
UPDATED, SKIPPED, KEYFRAME = 'updated', 'skipped', 'keyframe'


@dataclass
class FilterStats:
    """Frames seen, used, skipped, and keyframes made."""

    frames: int = 0
    updated: int = 0
    skipped: int = 0
    keyframes: int = 0


class DepthFilter:
    """Per-pixel Gaussian x uniform inverse-depth filter over a posed image stream."""

    def __init__(
        self,
        camera: PinholeCamera,
        config: FilterConfig | None = None,
        matching: MultiViewConfig | None = None,
        device: str | torch.device = 'cpu',
    ) -> None:
        self.camera = camera
        self.config = config or FilterConfig()
        self.config.validate()
        self.matching = matching or MultiViewConfig()
        self.matching.validate()
        self.device = torch.device(device)
        #: The search's chunk budget: ``multi_view.chunk_elements`` on CPU, at least
        #: ``CUDA_CHUNK_ELEMENTS`` on an accelerator, as the sweep's (kernel launches dominate
        #: there; the results do not depend on the chunk size).
        self._chunk_elements = effective_chunk_elements(self.matching.chunk_elements, self.device)
        self.rho_range = self.matching.rho_range
        self.margin = float(patch_reach(self.matching.patch, self.matching.patch_stride))
        self.key: FilterKeyframe | None = None
        self._scene = self.config.scene_depth  # scene_depth() of the frame being processed
        self.stats = FilterStats()
        #: Seconds per stage of :meth:`process` (``clock.enabled = True`` to record; the bench does).
        self.clock = StageClock(self.device)
        self._candidates = dataclasses.replace(
            self.matching,
            max_candidate_fraction=self.config.max_candidate_fraction,
            min_gradient=self.config.min_gradient,
        )

    # --- public -------------------------------------------------------------------------------

    def process(self, gray: np.ndarray, pose: np.ndarray) -> str:
        """Feed one posed frame (grey float in [0, 1] or uint8, camera-to-world 4x4), in stream order.

        Returns what was done: ``'updated'``, ``'skipped'`` (too little baseline or too much
        rotation) or ``'keyframe'`` (it became the filter's keyframe). Bad inputs raise
        ``ValueError`` naming them.
        """
        self.clock.switch('other')
        try:
            return self._process(gray, pose)
        finally:
            self.clock.stop()

    def _process(self, gray: np.ndarray, pose: np.ndarray) -> str:
        T_wf = validate_pose(pose, 'frame pose')
        image = torch.as_tensor(_as_gray(gray, 'frame image', self.camera), device=self.device)
        self.stats.frames += 1
        describe = lambda: self._describe(image)  # noqa: E731
        with torch.no_grad():
            if self.key is None:
                self.key = self._new_keyframe(image, describe(), T_wf)
                self.key.first = True
                self.stats.keyframes += 1
                return KEYFRAME
            key = self.key
            T_fk = relative_pose(key.pose, T_wf)
            self._scene = self.scene_depth()
            parallax = float(np.linalg.norm(T_fk[:3, 3])) / self._scene
            rotation = math.degrees(rotation_angle(T_fk[:3, :3]))
            usable = parallax >= self.config.min_parallax and rotation <= self.config.max_rotation_deg
            # A skipped frame needs no descriptors unless it becomes the keyframe.
            desc = describe() if usable else None
            seen = self._update(key, desc, T_fk) if usable else self._visible_fraction(key, T_fk)
            switch = (
                parallax >= self.config.keyframe_parallax
                or rotation >= self.config.keyframe_rotation_deg
                or seen < self.config.keyframe_min_visible
            )
            if switch:
                self.key = self._propagate(key, image, describe() if desc is None else desc, T_wf)
                self.stats.keyframes += 1
                return KEYFRAME
        if usable:
            self.stats.updated += 1
            return UPDATED
        self.stats.skipped += 1
        return SKIPPED

    def result(self, pose: np.ndarray | None = None, keyframe: FilterKeyframe | None = None) -> FilterResult:
        """Published estimates in the filter's keyframe, or warped into the camera at ``pose``.

        ``keyframe``: an earlier keyframe state (``self.key`` as it was before a switch) instead
        of the current one; a fixed-lag read uses it to keep what left the view.
        """
        cam = self.camera
        shape = cam.height * cam.width
        key = self.key if keyframe is None else keyframe
        if key is None:
            none = torch.zeros(0, device=self.device)
            return assemble_result(
                cam,
                none.long(),
                none,
                none,
                none,
                none,
                none,
                torch.zeros(shape, dtype=torch.bool, device=self.device),
            )
        published, withheld = self._published(key)
        rows = torch.nonzero(published, as_tuple=True)[0]
        st = key.state
        mu, var = st.mu[rows], st.var[rows]
        T_tk = None if pose is None else relative_pose(key.pose, validate_pose(pose, 'result pose'))
        if T_tk is None or np.allclose(T_tk, np.eye(4), atol=1e-9):
            target = key.flat[rows]
        else:
            warped = warp_estimates(key.us[rows], key.vs[rows], mu, cam.K, T_tk, cam.size, self.rho_range)
            rows = rows[warped.source]
            target, mu, var = warped.target, warped.rho, var[warped.source] * warped.scale**4
        candidates = torch.zeros(shape, dtype=torch.bool, device=self.device)
        candidates[target] = True
        return assemble_result(
            cam,
            target,
            mu,
            var,
            st.inlier_ratio[rows],
            key.updates[rows],
            key.cost[rows],
            candidates,
            self.config.score_relative_power,
            withheld_fraction=withheld,
        )

    def refocus(self, camera: PinholeCamera) -> bool:
        """Go on with ``camera`` when it differs from the current one only in its focal lengths
        (the focal check's correction, ``multiview/focal_check.py``), instead of starting over.

        The estimates so far were triangulated with the old focal length, off by an amount
        that depends on the motion (3 % in depth for a focal length 10 % long on the sideways
        stress walk, not 10 %), so they are kept as they are but made no more certain than the
        change: each inverse depth's standard deviation is at least ``|1 - scale|`` of it. The
        next frames, with the new focal length, then move them. Measured on the `wrong_focal`
        stream switched at frame 90 (docs/multi_view.md, "The focal length check"): median
        |log error| 0.016 five frames on and 0.008 at the end, where starting over left the
        next two keyframes without estimates and ended at 0.011, and rescaling the inverse
        depths by the focal change overshot (-6 %). Returns ``False`` (nothing changed) when
        the size or the principal point differ too.
        """
        old = self.camera
        if camera.size != old.size or (camera.cx, camera.cy) != (old.cx, old.cy):
            return False
        change = abs(1.0 - math.sqrt((camera.fx / old.fx) * (camera.fy / old.fy)))
        if self.key is not None:
            state = self.key.state
            state.var = torch.maximum(state.var, (state.mu * change) ** 2)
        self.camera = camera
        return True

    def scene_depth(self) -> float:
        """Median depth of the current estimates (m), or ``filter.scene_depth`` before any exists."""
        if self.key is not None:
            has = self.key.updates > 0
            if int(has.sum()) >= 50:
                # Every 4th pixel: a scale for the parallax tests, at a quarter of the sort.
                mu = self.key.state.mu[::4][has[::4]]
                return float(1.0 / torch.median(mu if mu.numel() > 0 else self.key.state.mu[has]))
        return self.config.scene_depth

    # --- steps --------------------------------------------------------------------------------

    def _describe(self, image: torch.Tensor) -> torch.Tensor:
        """The frame's matching descriptors (``stage_descriptors``, as the sweep's), on CPU
        stored channels-last.

        Why channels-last: every search sample reads all channels at its four bilinear taps;
        stored channel after channel those are seven planes apart, interleaved they share a
        cache line or two. On the searches of TUM fr1_xyz that makes ``grid_sample`` about a
        fifth cheaper (same numbers: only the memory layout changes); the descriptors are
        written so in the first place (no copy). On CUDA the layout is left as it is (not
        measured).
        """
        left = self.clock.switch('descriptors')
        desc = stage_descriptors(image[None], self.matching, channels_last=image.device.type == 'cpu')
        self.clock.switch(left)
        return desc

    def _published(self, key: FilterKeyframe) -> tuple[torch.Tensor, float | None]:
        """The estimates to publish, and the share of the measured ones that passed the
        precision test when that share was under ``min_published_fraction`` (then nothing is
        published; None otherwise)."""
        c, st = self.config, key.state
        need = max(c.min_updates, c.first_keyframe_min_updates) if key.first else c.min_updates
        measured = (key.updates >= need) & (st.inlier_ratio >= c.publish_inlier_ratio)
        published = (
            measured
            & (torch.sqrt(st.var) <= c.max_relative_sigma * st.mu)
            & (st.mu >= self.rho_range[0])
            & (st.mu <= self.rho_range[1])
        )
        # A sliver passing the precision test is the tail the noise selected (min_published_fraction).
        count, total = float(published.sum()), float(measured.sum())
        if 0 < count < c.min_published_fraction * total:
            return torch.zeros_like(published), count / total
        return published, None

    def _fresh_state(self, m: int) -> tuple[BetaGaussian, torch.Tensor, torch.Tensor]:
        lo, hi = self.rho_range
        full = lambda value: torch.full((m,), float(value), device=self.device)  # noqa: E731
        state = BetaGaussian(
            full(0.5 * (lo + hi)), full((hi - lo) ** 2), full(self.config.init_a), full(self.config.init_b)
        )
        return state, torch.zeros(m, dtype=torch.long, device=self.device), full(math.nan)

    def _new_keyframe(self, image: torch.Tensor, desc: torch.Tensor, T_wk: np.ndarray) -> FilterKeyframe:
        # One blur for the candidate test and the gradients (candidate_mask's own smoothing).
        smooth = gaussian_blur(image[None], self.matching.blur_sigma)[0]
        cand = candidate_mask(image, self._candidates, smooth=smooth)
        vs, us = torch.nonzero(cand, as_tuple=True)
        width = self.camera.width
        flat = vs * width + us
        # Candidates lie away from the border, so the central differences stay inside. Flat
        # index_select gathers: the same values as 2-D advanced indexing, several times cheaper.
        pixels = smooth.reshape(-1)
        at = lambda offset: pixels.index_select(0, flat + offset)  # noqa: E731
        grad = torch.stack(((at(1) - at(-1)) * 0.5, (at(width) - at(-width)) * 0.5))
        channels = desc.shape[1] - 1
        if desc.is_contiguous(memory_format=torch.channels_last):  # CPU (_describe): channels adjoin
            key_desc = desc[0].permute(1, 2, 0).reshape(-1, channels + 1).index_select(0, flat)
            key_desc = key_desc[:, :channels].T.contiguous()
        else:
            key_desc = desc[0, :channels].reshape(channels, -1).index_select(1, flat)
        state, updates, cost = self._fresh_state(int(flat.numel()))
        return FilterKeyframe(
            T_wk,
            desc,
            flat,
            us.float(),
            vs.float(),
            key_desc,
            grad,
            state,
            updates,
            torch.zeros_like(updates, dtype=torch.bool),
            cost,
            torch.zeros_like(updates),
        )

    def _visible_fraction(self, key: FilterKeyframe, T_fk: np.ndarray) -> float:
        has = torch.nonzero(key.updates > 0, as_tuple=True)[0]
        if has.numel() == 0:
            return 1.0
        warped = warp_estimates(
            key.us[has],
            key.vs[has],
            key.state.mu[has],
            self.camera.K,
            T_fk,
            self.camera.size,
            (0.0, math.inf),
        )
        # The z-buffer drops occluded duplicates; count sources that land at all.
        return float(warped.source.numel()) / float(has.numel())

    def _propagate(
        self, old: FilterKeyframe, image: torch.Tensor, desc: torch.Tensor, T_wn: np.ndarray
    ) -> FilterKeyframe:
        """New keyframe at this frame: carried estimates where they land, first measurements elsewhere."""
        left = self.clock.switch('propagation')
        new = self._new_keyframe(image, desc, T_wn)
        c = self.config
        rows = torch.nonzero(old.updates > 0, as_tuple=True)[0]
        new.first = old.first and rows.numel() == 0  # nothing to carry: still the stream's first
        T_nk = relative_pose(old.pose, T_wn)
        warped = warp_estimates(
            old.us[rows],
            old.vs[rows],
            old.state.mu[rows],
            self.camera.K,
            T_nk,
            self.camera.size,
            self.rho_range,
        )
        position = torch.full(
            (self.camera.width * self.camera.height,), -1, dtype=torch.long, device=self.device
        )
        position.index_copy_(0, new.flat, torch.arange(new.flat.numel(), device=self.device))
        # Reads by index_select (the same values as advanced indexing, several times cheaper on
        # CPU); the writes stay index_put_, as before (a tie in the z-buffer can repeat a target).
        at = position.index_select(0, warped.target)
        landed = torch.nonzero(at >= 0, as_tuple=True)[0]
        sources = rows.index_select(0, warped.source)
        kept = lambda t: t.index_select(0, landed)  # noqa: E731
        at, src, rho, scale4 = kept(at), kept(sources), kept(warped.rho), kept(warped.scale) ** 4
        old_at = lambda t: t.index_select(0, src)  # noqa: E731
        st = new.state
        st.mu[at] = rho
        inflated = old_at(old.state.var) * scale4 * c.propagation_inflation
        st.var[at] = inflated + (c.propagation_relative_sigma * rho) ** 2
        st.a[at] = old_at(old.state.a)
        st.b[at] = old_at(old.state.b)
        new.updates[at] = old_at(old.updates)
        new.prior[at] = True
        new.cost[at] = old_at(old.cost)
        # Only estimates with fill_min_updates measurements fill holes: a young one may be wrong,
        # and a prior filled from it is confirmed by the short searches around it.
        mature = torch.nonzero(old.updates.index_select(0, sources) >= c.fill_min_updates, as_tuple=True)[0]
        variance = old.state.var.index_select(0, sources) * warped.scale**4
        filled = self._fill_holes(
            new,
            warped.target.index_select(0, mature),
            warped.rho.index_select(0, mature),
            variance.index_select(0, mature),
        )
        # Pixels without a prior: a first measurement from the previous keyframe image.
        T_ok = relative_pose(T_wn, old.pose)
        if float(np.linalg.norm(T_ok[:3, 3])) / self._scene >= c.min_parallax:
            self._update(new, old.desc, T_ok, only=new.updates == 0)
        log.debug(
            'filter keyframe: %d carried of %d, %d filled, %d pixels',
            int(at.numel()),
            int(rows.numel()),
            filled,
            int(new.flat.numel()),
        )
        self.clock.switch(left)
        return new

    def _fill_holes(
        self, new: FilterKeyframe, target: torch.Tensor, rho: torch.Tensor, var: torch.Tensor
    ) -> int:
        """A prior for new pixels among carried estimates: the mean of those within ``fill_radius``.

        LSD-SLAM fills the holes that nearest-pixel propagation leaves (rounding, new
        candidates between carried ones) from their neighbours. The prior's variance is the
        neighbours' mean variance plus their spread (large across a depth edge), inflated as
        a propagation; it counts as no measurement (``updates`` stays 0), so the pixel is
        published only after frames confirm it, but it gets a short search instead of a
        whole-range one. Returns the number of pixels filled.
        """
        c = self.config
        if c.fill_radius <= 0 or target.numel() == 0:
            return 0
        h, w = self.camera.height, self.camera.width
        maps = torch.zeros((4, h * w), dtype=rho.dtype, device=rho.device)
        maps[0, target] = 1.0
        maps[1, target] = rho
        maps[2, target] = rho * rho
        maps[3, target] = var
        sums = box_sum(maps.view(4, h, w), c.fill_radius).view(4, h * w).index_select(1, new.flat)
        n = sums[0]
        hole = ~new.prior & (n >= c.fill_min_neighbours)
        n = torch.clamp(n, min=1.0)
        mean = sums[1] / n
        spread = torch.clamp(sums[2] / n - mean * mean, min=0.0)
        fill_var = (sums[3] / n + spread) * c.propagation_inflation + (
            c.propagation_relative_sigma * mean
        ) ** 2
        st = new.state
        st.mu = torch.where(hole, mean, st.mu)
        st.var = torch.where(hole, fill_var, st.var)
        new.prior = new.prior | hole
        return int(hole.sum())

    def _tau2(self, rho: torch.Tensor, j: torch.Tensor, baseline: float) -> torch.Tensor:
        """Measurement variance: one ``pixel_sigma`` of matching error back-propagated through the
        epipolar motion ``j``, plus the pose noise as a relative error ``pose_sigma / baseline``."""
        c = self.config
        tau2 = (c.pixel_sigma / torch.clamp(j, min=1e-6)) ** 2
        if c.pose_sigma == 0.0:  # the default: the term is + 0 (its three passes were a tenth of an update)
            return tau2
        return tau2 + (rho * (c.pose_sigma / baseline)) ** 2

    def _update(
        self, key: FilterKeyframe, desc: torch.Tensor, T_fk: np.ndarray, only: torch.Tensor | None = None
    ) -> float:
        """One frame's measurements for the pixels of ``key`` it can teach something, in place.

        Cheap per-pixel tests on every pixel first (:meth:`_choose`), then the searches and the
        update on the chosen rows only, scattered back: the frame's cost follows the pixels
        that still need it, not the candidate count. Returns the fraction of the estimates
        that project into the frame (the keyframe-switch test), from the same projection.
        ``only``: the new keyframe's first measurements at a switch (its stages are the
        ``seed`` ones of :attr:`clock`).
        """
        prefix = 'seed ' if only is not None else ''
        left = self.clock.switch(prefix + 'selection')
        try:
            return self._update_rows(key, desc, T_fk, only, prefix)
        finally:
            self.clock.switch(left)

    def _update_rows(
        self,
        key: FilterKeyframe,
        desc: torch.Tensor,
        T_fk: np.ndarray,
        only: torch.Tensor | None,
        prefix: str,
    ) -> float:
        """:meth:`_update`'s work; ``prefix`` names its stages."""
        c = self.config
        rho_min, rho_max = self.rho_range
        st = key.state
        baseline = max(float(np.linalg.norm(T_fk[:3, 3])), 1e-9)
        geo = frame_geometry(key, self.camera, T_fk, self.margin)
        rows, seen = self._choose(key, geo, baseline, only)
        if rows.numel() == 0:
            return seen
        # Everything below runs on the chosen rows only (index_select: several times faster
        # on CPU than advanced indexing).
        pick = lambda t: t.index_select(0, rows)  # noqa: E731
        a_r, j_r = geo.a.index_select(1, rows), pick(geo.j)
        mu_r, var_r, f_r = pick(st.mu), pick(st.var), ~pick(key.prior)
        # The rows without a prior, once: the whole-range bounds, the search's spans and the
        # first measurements are index ops on these few rows instead of where over all rows
        # (torch.where is several times slower than arithmetic on CPU).
        seeds = torch.nonzero(f_r, as_tuple=True)[0]
        floor = c.min_search_px / torch.clamp(j_r, min=1e-9)
        half = torch.maximum(c.search_sigmas * torch.sqrt(var_r), floor)
        lo = torch.clamp(mu_r - half, rho_min, rho_max).index_fill_(0, seeds, rho_min)
        hi = torch.clamp(mu_r + half, rho_min, rho_max).index_fill_(0, seeds, rho_max)
        bracketed = self._bracket(key, rows, seeds, f_r, a_r, geo.b, lo, hi)
        self.clock.switch(prefix + 'search')
        x, cost, valid = self._search(key, rows, desc, a_r, geo, lo, hi, j_r, f_r, seeds)
        self.clock.switch(prefix + 'update')
        # The epipolar motion at the match: the bracket's edge test and the measurement
        # variance (only read where the match is valid, so one evaluation at x serves both).
        j_x = row_motion(a_r, geo.b, x)
        if bracketed is not None:
            # A bracket's best match on its edge: the minimum lies outside, not a measurement.
            inside = ((x - lo) * j_x >= 0.5) & ((hi - x) * j_x >= 0.5)
            valid &= ~bracketed | inside
        valid &= (x >= rho_min) & (x <= rho_max)
        valid &= j_x > 1e-6
        tau2 = self._tau2(x, j_x, baseline)
        fail = ~f_r & ~valid  # visible (chosen above) but nothing matched: an outlier vote
        a_old, b_old = pick(st.a), pick(st.b)
        prior = BetaGaussian(mu_r, var_r, a_old, b_old)
        # The posterior of every row; only the valid ones keep it (the others' inputs, and so
        # their posterior, are not read), and a valid row without a prior takes its first
        # measurement instead, below.
        post = gaussian_uniform_update(prior, x, tau2, self.rho_range)
        mu_n = torch.where(valid, post.mu, mu_r)
        var_n = torch.where(valid, post.var, var_r)
        a_n = torch.where(valid, post.a, a_old)
        b_n = torch.where(valid, post.b, outlier_vote(prior, fail).b)
        born = seeds.masked_select(valid.index_select(0, seeds))  # first measurements
        if born.numel() > 0:
            mu_n.index_copy_(0, born, x.index_select(0, born))
            var_n.index_copy_(0, born, tau2.index_select(0, born))
            a_n.index_fill_(0, born, c.init_a)
            b_n.index_fill_(0, born, c.init_b)
        n_n = pick(key.updates) + valid.long()
        prior_n = ~f_r | valid
        # Outliers: a pixel that keeps failing is reset to "no estimate" (it may be re-seeded).
        gone = torch.nonzero(~f_r & (a_n / (a_n + b_n) < c.min_inlier_ratio), as_tuple=True)[0]
        if gone.numel() > 0:
            mid, span2 = 0.5 * (rho_min + rho_max), (rho_max - rho_min) ** 2  # _fresh_state's values
            for value, fill in (
                (mu_n, mid),
                (var_n, span2),
                (a_n, c.init_a),
                (b_n, c.init_b),
                (n_n, 0),
                (prior_n, False),
            ):
                value.index_fill_(0, gone, fill)
        for target, value in (
            (st.mu, mu_n),
            (st.var, var_n),
            (st.a, a_n),
            (st.b, b_n),
            (key.updates, n_n),
            (key.prior, prior_n),
            (key.cost, torch.where(valid, cost, pick(key.cost))),
        ):
            target.scatter_(0, rows, value)  # rows are distinct: index_copy_'s result, a third cheaper
        return seen

    def _bracket(
        self,
        key: FilterKeyframe,
        rows: torch.Tensor,
        seeds: torch.Tensor,
        fresh: torch.Tensor,
        a_r: torch.Tensor,
        b: tuple[float, float, float],
        lo: torch.Tensor,
        hi: torch.Tensor,
    ) -> torch.Tensor | None:
        """First attempt of a pixel without an estimate: its neighbours' range, not the whole range.

        A new pixel next to measured ones (within ``seed_radius`` px) most likely lies on
        their surface: its first search spans the neighbours' inverse depths, widened by
        ``2 min_search_px`` px each side, a few samples instead of a whole-range search
        (its second attempt, if this one fails, is a whole-range one). ``lo``, ``hi`` are
        narrowed in place; returns which rows were bracketed (None: none). ``seeds``: the rows
        of ``fresh`` (the first attempts are among them: tested on those few rows only).
        """
        c = self.config
        if c.seed_radius <= 0 or seeds.numel() == 0:
            return None
        # _choose counted this attempt
        sel = seeds.masked_select(key.attempts.index_select(0, rows.index_select(0, seeds)) == 1)
        if sel.numel() == 0 or not bool(key.updates.any()):  # updates >= 0: any() is "any > 0"
            return None
        n_lo, n_hi = self._neighbour_range(key, rows.index_select(0, sel))
        near = torch.isfinite(n_lo)
        sel, n_lo, n_hi = sel[near], n_lo[near], n_hi[near]
        a_s = a_r.index_select(1, sel)
        rho_min, rho_max = self.rho_range
        pad = 2.0 * c.min_search_px
        lo.index_copy_(
            0,
            sel,
            torch.clamp(n_lo - pad / torch.clamp(row_motion(a_s, b, n_lo), min=1e-9), rho_min, rho_max),
        )
        hi.index_copy_(
            0,
            sel,
            torch.clamp(n_hi + pad / torch.clamp(row_motion(a_s, b, n_hi), min=1e-9), rho_min, rho_max),
        )
        use = torch.zeros_like(fresh)
        use[sel] = True
        return use

    def _neighbour_range(self, key: FilterKeyframe, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Lowest and highest measured inverse depth within ``seed_radius`` px of each row's
        pixel (``inf``, ``-inf`` where none): the (2r + 1)^2 window of each row, gathered
        through the keyframe's padded pixel-to-row map, so the cost follows the rows asked
        for, not the image."""
        r = self.config.seed_radius
        h, w = self.camera.height, self.camera.width
        if int(rows.numel()) * (2 * r + 1) ** 2 > h * w:
            return self._neighbour_range_dense(key, rows)
        wp = w + 2 * r
        m = int(key.flat.numel())
        if key.padded_rows is None or key.padded_flat is None:  # once per keyframe
            key.padded_flat = (key.vs.long() + r) * wp + key.us.long() + r
            key.padded_rows = torch.full(((h + 2 * r) * wp,), m, dtype=torch.long, device=self.device)
            key.padded_rows.index_copy_(0, key.padded_flat, torch.arange(m, device=self.device))
        d = torch.arange(-r, r + 1, device=self.device)
        offsets = (d[:, None] * wp + d[None, :]).reshape(-1)
        window = (key.padded_flat.index_select(0, rows)[:, None] + offsets[None, :]).reshape(-1)
        near = key.padded_rows.index_select(0, window)  # rows, m for "no candidate there"
        # Gathered first, then "no estimate" where there is no candidate (near == m): the
        # window's entries only, not a copy of the keyframe's state with a spare entry.
        inside = near.clamp(max=m - 1)
        mu = key.state.mu.index_select(0, inside)
        has = (key.updates.index_select(0, inside) > 0) & (near < m)
        shape = (int(rows.numel()), int(offsets.numel()))
        lows = torch.where(has, mu, math.inf).view(shape).amin(dim=1)
        highs = torch.where(has, mu, -math.inf).view(shape).amax(dim=1)
        return lows, highs

    def _neighbour_range_dense(
        self, key: FilterKeyframe, rows: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`_neighbour_range` through a min and a max filter over the whole image, for many
        rows (a new keyframe's seeds): its windows would gather more entries than the image
        has pixels. Minima and maxima are exact, so the numbers are the same."""
        r = self.config.seed_radius
        h, w = self.camera.height, self.camera.width
        has = key.updates > 0
        ranges = []
        for empty, pick in ((math.inf, torch.minimum), (-math.inf, torch.maximum)):
            image = torch.full((h * w,), empty, dtype=key.state.mu.dtype, device=self.device)
            image.scatter_(0, key.flat, torch.where(has, key.state.mu, empty))
            padded = F.pad(image.view(1, h, w), (r, r, r, r), value=empty)[0]
            window = window_reduce(padded, r, lambda acc, x, pick=pick: pick(acc, x, out=acc))
            ranges.append(window.view(-1).index_select(0, key.flat.index_select(0, rows)))
        return ranges[0], ranges[1]

    def _choose(
        self, key: FilterKeyframe, geo: FrameGeometry, baseline: float, only: torch.Tensor | None
    ) -> tuple[torch.Tensor, float]:
        """Rows this frame searches, and the fraction of the estimates it sees.

        LSD-SLAM: only where the gradient has a component along the epipolar line. REMODE:
        converged pixels this frame cannot improve are left alone. Whole-range searches only
        from frames with ``seed_parallax`` and ``seed_attempts`` left. Pixels without a prior
        are searched from the middle of the range (``mu`` holds it: :meth:`_fresh_state`), so
        their projection only gives the epipolar direction.
        """
        c = self.config
        st = key.state
        fresh = ~key.prior
        estimates = key.prior  # a measured, carried or filled prior
        want = (geo.along >= c.min_epipolar_gradient) & (fresh | geo.visible)
        want &= fresh | (st.var >= c.min_information * self._tau2(st.mu, geo.j, baseline))
        seeding = baseline / self._scene >= c.seed_parallax
        if seeding:
            want &= estimates | (key.attempts < c.seed_attempts)
        else:
            want &= estimates
        if only is not None:
            want &= only
        seeds = want & fresh
        key.attempts += seeds.long()
        n_estimates = float(estimates.sum())
        seen = float((geo.visible & estimates).sum()) / n_estimates if n_estimates > 0 else 1.0
        return torch.nonzero(want, as_tuple=True)[0], seen

    def _search(
        self,
        key: FilterKeyframe,
        rows: torch.Tensor,
        desc: torch.Tensor,
        a_r: torch.Tensor,
        geo: FrameGeometry,
        lo: torch.Tensor,
        hi: torch.Tensor,
        j_r: torch.Tensor,
        fresh: torch.Tensor,
        seeds: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Search each chosen row in ``[lo, hi]``, in buckets by sample count (``plan_buckets``).

        Returns the match ``x``, its cost and whether it passed ``max_cost`` (and, in the
        buckets with a distinctiveness test, ``min_distinctiveness``; with
        ``reject_edge_minima``, lay inside its interval), per row.
        """
        c = self.config
        # Interval length in px: to first order at the prior mean for an estimate (as the
        # +-2 px floor is set); a whole-range search takes the larger motion of its two ends.
        span = j_r * (hi - lo)
        if seeds.numel() > 0:  # the rows of ``fresh``
            a_s, lo_s, hi_s = a_r.index_select(1, seeds), lo.index_select(0, seeds), hi.index_select(0, seeds)
            ends = torch.maximum(row_motion(a_s, geo.b, lo_s), row_motion(a_s, geo.b, hi_s))
            span.index_copy_(0, seeds, ends * (hi_s - lo_s))
        bucket = plan_buckets(span, fresh, c)
        # Rows sorted by bucket once: each bucket is then a slice (views, no gather per bucket),
        # and the results go back in one scatter.
        members = [torch.nonzero(bucket == k, as_tuple=True)[0] for k in range(len(search_buckets(c)))]
        order = torch.cat(members)  # a counting sort: torch.argsort is several times slower on CPU
        counts = [int(m.numel()) for m in members]
        desc_o = key.key_desc.index_select(1, rows.index_select(0, order))
        lo_o, hi_o = lo.index_select(0, order), hi.index_select(0, order)
        # The rays normalised once for the frame, not once per bucket.
        a_o, b_o = grid_rows_in_place(
            a_r.index_select(1, order), geo.b, self.camera.width, self.camera.height
        )
        xs, costs, goods = [], [], []
        start = 0
        for (samples, refine, distinct), n in zip(search_buckets(c), counts, strict=True):
            if n == 0:
                continue
            stop = start + n
            found = search_interval(
                desc_o[:, start:stop],
                desc,
                (a_o[:, start:stop], b_o),
                lo_o[start:stop],
                hi_o[start:stop],
                samples,
                refine,
                self._chunk_elements,
                with_distinctiveness=distinct,
                reject_edges=c.reject_edge_minima,
            )
            good = found.ok & (found.cost <= c.max_cost)
            if distinct:
                good &= found.distinct >= c.min_distinctiveness
            xs.append(found.rho)
            costs.append(found.cost)
            goods.append(good)
            start = stop
        x = torch.empty_like(lo).scatter_(0, order, torch.cat(xs))
        cost = torch.empty_like(lo).scatter_(0, order, torch.cat(costs))
        valid = torch.empty_like(fresh).scatter_(0, order, torch.cat(goods))
        return x, cost, valid
