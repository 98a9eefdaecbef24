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
   least +-2 px; the whole range for a pixel without a prior), ``filter_search``; the match
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
from ..geometry import relative_pose, rotation_angle, validate_pose
from .cost_volume import EpipolarRays, epipolar_rays, gaussian_blur, patch_reach, stage_descriptors
from .filter_config import FilterConfig
from .filter_propagate import warp_estimates
from .filter_result import FilterResult, assemble_result
from .filter_search import search_interval
from .filter_update import BetaGaussian, gaussian_uniform_update, outlier_vote
from .semidense import MultiViewConfig, candidate_mask
from .views import _as_gray

log = logging.getLogger(__name__)

#: What :meth:`DepthFilter.process` did with a frame.
UPDATED, SKIPPED, KEYFRAME = 'updated', 'skipped', 'keyframe'


@dataclass
class _Keyframe:
    """The filter's keyframe: image descriptors, candidate pixels and their posterior."""

    pose: np.ndarray  # T_wk
    desc: torch.Tensor  # (1, C + 1, H, W) descriptors of the whole image (the next keyframe's observation)
    flat: torch.Tensor  # (M,) long pixel index v * W + u
    us: torch.Tensor
    vs: torch.Tensor
    key_desc: torch.Tensor  # (C, M)
    grad: torch.Tensor  # (2, M) grey gradient (gx, gy) per px after the matching blur
    state: BetaGaussian
    updates: torch.Tensor  # (M,) measurements fused (0 = no estimate yet)
    prior: torch.Tensor  # (M,) bool: mu, var hold a prior (measured, carried or filled): short searches
    cost: torch.Tensor  # (M,) last matching cost
    attempts: torch.Tensor  # (M,) long searches spent on a pixel without an estimate


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
        self.rho_range = self.matching.rho_range
        self.margin = float(patch_reach(self.matching.patch, self.matching.patch_stride))
        self.key: _Keyframe | None = None
        self._scene = self.config.scene_depth  # scene_depth() of the frame being processed
        self.stats = FilterStats()
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
        T_wf = validate_pose(pose, 'frame pose')
        image = torch.as_tensor(_as_gray(gray, 'frame image', self.camera), device=self.device)
        self.stats.frames += 1
        with torch.no_grad():
            desc = stage_descriptors(image[None], self.matching)
            if self.key is None:
                self.key = self._new_keyframe(image, desc, T_wf)
                self.stats.keyframes += 1
                return KEYFRAME
            key = self.key
            T_fk = relative_pose(key.pose, T_wf)
            self._scene = self.scene_depth()
            parallax = float(np.linalg.norm(T_fk[:3, 3])) / self._scene
            rotation = math.degrees(rotation_angle(T_fk[:3, :3]))
            usable = parallax >= self.config.min_parallax and rotation <= self.config.max_rotation_deg
            seen = self._update(key, desc, T_fk) if usable else self._visible_fraction(key, T_fk)
            switch = (
                parallax >= self.config.keyframe_parallax
                or rotation >= self.config.keyframe_rotation_deg
                or seen < self.config.keyframe_min_visible
            )
            if switch:
                self.key = self._propagate(key, image, desc, T_wf)
                self.stats.keyframes += 1
                return KEYFRAME
        if usable:
            self.stats.updated += 1
            return UPDATED
        self.stats.skipped += 1
        return SKIPPED

    def result(self, pose: np.ndarray | None = None, keyframe: _Keyframe | None = None) -> FilterResult:
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
                cam, none.long(), none, none, none, none, none, torch.zeros(shape, dtype=torch.bool)
            )
        rows = torch.nonzero(self._published(key), as_tuple=True)[0]
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
        )

    def scene_depth(self) -> float:
        """Median depth of the current estimates (m), or ``filter.scene_depth`` before any exists."""
        if self.key is not None:
            has = self.key.updates > 0
            if int(has.sum()) >= 50:
                return float(1.0 / torch.median(self.key.state.mu[has]))
        return self.config.scene_depth

    # --- steps --------------------------------------------------------------------------------

    def _published(self, key: _Keyframe) -> torch.Tensor:
        c, st = self.config, key.state
        return (
            (key.updates >= c.min_updates)
            & (st.inlier_ratio >= c.publish_inlier_ratio)
            & (torch.sqrt(st.var) <= c.max_relative_sigma * st.mu)
            & (st.mu >= self.rho_range[0])
            & (st.mu <= self.rho_range[1])
        )

    def _fresh_state(self, m: int) -> tuple[BetaGaussian, torch.Tensor, torch.Tensor]:
        lo, hi = self.rho_range
        full = lambda value: torch.full((m,), float(value), device=self.device)  # noqa: E731
        state = BetaGaussian(
            full(0.5 * (lo + hi)), full((hi - lo) ** 2), full(self.config.init_a), full(self.config.init_b)
        )
        return state, torch.zeros(m, dtype=torch.long, device=self.device), full(math.nan)

    def _new_keyframe(self, image: torch.Tensor, desc: torch.Tensor, T_wk: np.ndarray) -> _Keyframe:
        # One blur for the candidate test and the gradients (candidate_mask's own smoothing).
        smooth = gaussian_blur(image[None], self.matching.blur_sigma)[0]
        cand = candidate_mask(image, self._candidates, smooth=smooth)
        vs, us = torch.nonzero(cand, as_tuple=True)
        # Candidates lie away from the border, so the central differences stay inside.
        grad = torch.stack(
            ((smooth[vs, us + 1] - smooth[vs, us - 1]) * 0.5, (smooth[vs + 1, us] - smooth[vs - 1, us]) * 0.5)
        )
        flat = vs * self.camera.width + us
        channels = desc.shape[1] - 1
        state, updates, cost = self._fresh_state(int(flat.numel()))
        return _Keyframe(
            T_wk,
            desc,
            flat,
            us.float(),
            vs.float(),
            desc[0, :channels][:, vs, us],
            grad,
            state,
            updates,
            torch.zeros_like(updates, dtype=torch.bool),
            cost,
            torch.zeros_like(updates),
        )

    def _visible_fraction(self, key: _Keyframe, T_fk: np.ndarray) -> float:
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
        self, old: _Keyframe, image: torch.Tensor, desc: torch.Tensor, T_wn: np.ndarray
    ) -> _Keyframe:
        """New keyframe at this frame: carried estimates where they land, first measurements elsewhere."""
        new = self._new_keyframe(image, desc, T_wn)
        c = self.config
        rows = torch.nonzero(old.updates > 0, as_tuple=True)[0]
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
        position[new.flat] = torch.arange(new.flat.numel(), device=self.device)
        at = position[warped.target]
        landed = at >= 0
        at, src, rho = at[landed], rows[warped.source[landed]], warped.rho[landed]
        scale4 = warped.scale[landed] ** 4
        st = new.state
        st.mu[at] = rho
        st.var[at] = (
            old.state.var[src] * scale4 * c.propagation_inflation + (c.propagation_relative_sigma * rho) ** 2
        )
        st.a[at] = old.state.a[src]
        st.b[at] = old.state.b[src]
        new.updates[at] = old.updates[src]
        new.prior[at] = True
        new.cost[at] = old.cost[src]
        filled = self._fill_holes(
            new, warped.target, warped.rho, old.state.var[rows[warped.source]] * warped.scale**4
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
        return new

    def _fill_holes(self, new: _Keyframe, target: torch.Tensor, rho: torch.Tensor, var: torch.Tensor) -> int:
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
        sums = _box_sum(maps.view(4, h, w), c.fill_radius).view(4, h * w)[:, new.flat]
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
        return (c.pixel_sigma / torch.clamp(j, min=1e-6)) ** 2 + (rho * (c.pose_sigma / baseline)) ** 2

    def _update(
        self, key: _Keyframe, desc: torch.Tensor, T_fk: np.ndarray, only: torch.Tensor | None = None
    ) -> float:
        """One frame's measurements for the pixels of ``key`` it can teach something, in place.

        Cheap per-pixel tests on every pixel first (projection of the prior mean, gradient along
        the epipolar line, expected information, seeding budget), then the searches and the
        update on the chosen rows only, scattered back: the frame's cost follows the pixels
        that still need it, not the candidate count. Returns the fraction of the estimates
        that project into the frame (the keyframe-switch test), from the same projection.
        """
        c = self.config
        rho_min, rho_max = self.rho_range
        cam = self.camera
        st = key.state
        rays = epipolar_rays(key.us, key.vs, cam.K, T_fk[None], cam.size, self.device)
        fresh = ~key.prior
        baseline = max(float(np.linalg.norm(T_fk[:3, 3])), 1e-9)
        prior = torch.where(fresh, torch.full_like(st.mu, 0.5 * (rho_min + rho_max)), st.mu)
        pu, pv, front = (t[0, :, 0] for t in rays.project(prior[:, None]))
        m = self.margin
        visible = front & (pu >= m) & (pu <= cam.width - 1 - m) & (pv >= m) & (pv <= cam.height - 1 - m)
        du, dv = (t[0] for t in rays.motion(prior))
        j_mu = torch.hypot(du, dv)
        # LSD-SLAM: only where the gradient has a component along the epipolar line.
        along = (key.grad[0] * du + key.grad[1] * dv).abs() / torch.clamp(j_mu, min=1e-9)
        want = (along >= c.min_epipolar_gradient) & (fresh | visible)
        # REMODE: converged pixels this frame cannot improve are left alone.
        want &= fresh | (st.var >= c.min_information * self._tau2(st.mu, j_mu, baseline))
        seeding = baseline / self._scene >= c.seed_parallax
        want &= ~fresh | ((key.attempts < c.seed_attempts) & seeding)
        if only is not None:
            want &= only
        key.attempts = key.attempts + (want & fresh).long()
        estimates = ~fresh
        n_estimates = float(estimates.sum())
        seen = float((visible & estimates).sum()) / n_estimates if n_estimates > 0 else 1.0
        half = torch.maximum(c.search_sigmas * torch.sqrt(st.var), 2.0 / torch.clamp(j_mu, min=1e-9))
        lo = torch.where(fresh, torch.full_like(st.mu, rho_min), torch.clamp(st.mu - half, rho_min, rho_max))
        hi = torch.where(fresh, torch.full_like(st.mu, rho_max), torch.clamp(st.mu + half, rho_min, rho_max))
        # Interval length in pixels, to first order (the epipolar motion at the prior mean).
        short = ~fresh & (j_mu * (hi - lo) <= c.short_samples * c.max_step_px)
        x = torch.full_like(st.mu, math.nan)
        cost = torch.full_like(st.mu, math.inf)
        valid = torch.zeros_like(fresh)
        for mask, samples, refine, distinct in (
            (want & short, c.short_samples, 0, False),
            (want & ~short, c.long_samples, c.refine_samples, True),
        ):
            idx = torch.nonzero(mask, as_tuple=True)[0]
            if idx.numel() == 0:
                continue
            found = search_interval(
                key.key_desc[:, idx],
                desc,
                EpipolarRays(rays.a[:, idx], rays.b, rays.width, rays.height),
                lo[idx],
                hi[idx],
                samples,
                refine,
                self.matching.chunk_elements,
                with_distinctiveness=distinct,
            )
            good = found.ok & (found.cost <= c.max_cost)
            if distinct:
                good &= found.distinct >= c.min_distinctiveness
            x[idx], cost[idx], valid[idx] = found.rho, found.cost, good
        rows = torch.nonzero(want, as_tuple=True)[0]
        if rows.numel() == 0:
            return seen
        valid &= (x >= rho_min) & (x <= rho_max)
        xr = torch.where(valid, x, st.mu)
        j_x = torch.hypot(*(t[0] for t in rays.motion(xr)))
        valid &= j_x > 1e-6
        tau2 = self._tau2(xr, j_x, baseline)[rows]
        f_r, mu_r, var_r, valid, x, cost = (
            fresh[rows],
            st.mu[rows],
            st.var[rows],
            valid[rows],
            x[rows],
            cost[rows],
        )
        init, upd = f_r & valid, ~f_r & valid
        fail = ~f_r & ~valid  # visible (chosen above) but nothing matched: an outlier vote
        a_r, b_r = st.a[rows], st.b[rows]
        post = gaussian_uniform_update(
            BetaGaussian(mu_r, var_r, a_r, b_r),
            torch.where(upd, x, mu_r),
            torch.where(upd, tau2, var_r),
            self.rho_range,
        )
        mu_n = torch.where(init, x, torch.where(upd, post.mu, mu_r))
        var_n = torch.where(init, tau2, torch.where(upd, post.var, var_r))
        a_n = torch.where(init, torch.full_like(a_r, c.init_a), torch.where(upd, post.a, a_r))
        voted = outlier_vote(BetaGaussian(mu_r, var_r, a_r, b_r), fail).b
        b_n = torch.where(init, torch.full_like(b_r, c.init_b), torch.where(upd, post.b, voted))
        n_n = key.updates[rows] + (init | upd).long()
        # Outliers: a pixel that keeps failing is reset to "no estimate" (it may be re-seeded).
        drop = ~f_r & (a_n / (a_n + b_n) < c.min_inlier_ratio)
        reset, _, _ = self._fresh_state(int(rows.numel()))
        st.mu[rows] = torch.where(drop, reset.mu, mu_n)
        st.var[rows] = torch.where(drop, reset.var, var_n)
        st.a[rows] = torch.where(drop, reset.a, a_n)
        st.b[rows] = torch.where(drop, reset.b, b_n)
        key.updates[rows] = torch.where(drop, torch.zeros_like(n_n), n_n)
        key.prior[rows] = (key.prior[rows] | init) & ~drop
        key.cost[rows] = torch.where(init | upd, cost, key.cost[rows])
        return seen


def _box_sum(maps: torch.Tensor, r: int) -> torch.Tensor:
    """Sum of each ``(C, H, W)`` map over the ``(2r + 1)^2`` window (zeros outside): separable
    shifted slices, several times faster on CPU than ``avg_pool2d`` for these small windows."""
    h, w = maps.shape[-2:]
    padded = F.pad(maps, (r, r, r, r))
    rows = sum(padded[:, :, k : k + w] for k in range(2 * r + 1))
    return sum(rows[:, k : k + h, :] for k in range(2 * r + 1))
