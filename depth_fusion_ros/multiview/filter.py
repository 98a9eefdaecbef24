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
2. **Update**: each pixel is searched along its epipolar line in the frame within
   ``mu +- search_sigmas sigma`` (at least +-2 px; the whole range for a pixel without an
   estimate: the "coarse sweep" of a new pixel), ``filter_search``; the match gives a
   measurement ``x`` with variance ``tau^2 = (pixel_sigma / J)^2``, ``J`` the epipolar motion
   per unit inverse depth (one pixel of matching error back-propagated, as the sweep's
   geometric score). Then the Gaussian x uniform update; a visible pixel that matched
   nothing gets an outlier vote; a pixel whose inlier ratio drops below ``min_inlier_ratio``
   is reset to "no estimate".
3. **New keyframe** when the parallax reaches ``keyframe_parallax``, the rotation
   ``keyframe_rotation_deg`` or the visible fraction of the estimates falls below
   ``keyframe_min_visible``: the estimates are propagated into the frame
   (``filter_propagate``: warped mean, inflated variance, Beta carried), and the pixels
   left without a prior get their first measurement from the previous keyframe image.

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

from ..camera import PinholeCamera
from ..geometry import relative_pose, rotation_angle, validate_pose
from .cost_volume import EpipolarRays, epipolar_rays, patch_reach, stage_descriptors
from .filter_config import FilterConfig
from .filter_propagate import warp_estimates
from .filter_result import FilterResult, assemble_result
from .filter_search import SearchResult, search_interval
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
    state: BetaGaussian
    updates: torch.Tensor  # (M,) measurements fused (0 = no estimate yet)
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
        self.stats = FilterStats()
        self._candidates = dataclasses.replace(
            self.matching, max_candidate_fraction=self.config.max_candidate_fraction
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
            parallax = float(np.linalg.norm(T_fk[:3, 3])) / self.scene_depth()
            rotation = math.degrees(rotation_angle(T_fk[:3, :3]))
            usable = parallax >= self.config.min_parallax and rotation <= self.config.max_rotation_deg
            if usable:
                self._update(key, desc, T_fk)
            switch = (
                parallax >= self.config.keyframe_parallax
                or rotation >= self.config.keyframe_rotation_deg
                or self._visible_fraction(key, T_fk) < self.config.keyframe_min_visible
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

    def result(self, pose: np.ndarray | None = None) -> FilterResult:
        """Published estimates in the filter's keyframe, or warped into the camera at ``pose``."""
        cam = self.camera
        shape = cam.height * cam.width
        if self.key is None:
            none = torch.zeros(0, device=self.device)
            return assemble_result(
                cam, none.long(), none, none, none, none, none, torch.zeros(shape, dtype=torch.bool)
            )
        key = self.key
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
            cam, target, mu, var, st.inlier_ratio[rows], key.updates[rows], key.cost[rows], candidates
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
        cand = candidate_mask(image, self._candidates)
        vs, us = torch.nonzero(cand, as_tuple=True)
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
            state,
            updates,
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
        new.cost[at] = old.cost[src]
        # Pixels without a prior: a first measurement from the previous keyframe image.
        T_ok = relative_pose(T_wn, old.pose)
        if float(np.linalg.norm(T_ok[:3, 3])) / self.scene_depth() >= c.min_parallax:
            self._update(new, old.desc, T_ok, only=new.updates == 0)
        log.debug(
            'filter keyframe: %d carried of %d, %d pixels',
            int(at.numel()),
            int(rows.numel()),
            int(new.flat.numel()),
        )
        return new

    def _search(
        self,
        key: _Keyframe,
        desc: torch.Tensor,
        rays: EpipolarRays,
        interval: tuple[torch.Tensor, torch.Tensor],
        rows: torch.Tensor,
        samples: int,
        refine: int,
    ) -> SearchResult:
        sub = EpipolarRays(rays.a[:, rows], rays.b, rays.width, rays.height)
        lo, hi = interval
        return search_interval(
            key.key_desc[:, rows],
            desc,
            sub,
            lo[rows],
            hi[rows],
            samples,
            refine,
            self.matching.chunk_elements,
        )

    def _update(
        self, key: _Keyframe, desc: torch.Tensor, T_fk: np.ndarray, only: torch.Tensor | None = None
    ) -> None:
        """One frame's measurements for every (or every ``only``) pixel of ``key``, in place."""
        c = self.config
        rho_min, rho_max = self.rho_range
        cam = self.camera
        rays = epipolar_rays(key.us, key.vs, cam.K, T_fk[None], cam.size, self.device)
        st = key.state
        fresh = key.updates == 0
        active = torch.ones_like(fresh) if only is None else only
        j_mu = rays.parallax(st.mu)[0]
        half = torch.maximum(c.search_sigmas * torch.sqrt(st.var), 2.0 / torch.clamp(j_mu, min=1e-9))
        lo = torch.where(fresh, torch.full_like(st.mu, rho_min), torch.clamp(st.mu - half, rho_min, rho_max))
        hi = torch.where(fresh, torch.full_like(st.mu, rho_max), torch.clamp(st.mu + half, rho_min, rho_max))
        u, v, _ = rays.project(torch.stack((lo, hi), dim=1))
        length = torch.hypot(u[0, :, 1] - u[0, :, 0], v[0, :, 1] - v[0, :, 0])
        short = active & ~fresh & (length <= c.short_samples * c.max_step_px)
        # A pixel without an estimate is searched over the whole range only while it has
        # attempts left (texture-less candidates would otherwise cost a long search per frame).
        long = active & ~short & (key.attempts < c.seed_attempts)
        key.attempts = key.attempts + (long & fresh).long()
        x = torch.full_like(st.mu, math.nan)
        cost = torch.full_like(st.mu, math.inf)
        valid = torch.zeros_like(fresh)
        buckets = ((short, c.short_samples, 0, False), (long, c.long_samples, c.refine_samples, True))
        for mask, samples, refine, need_distinct in buckets:
            rows = torch.nonzero(mask, as_tuple=True)[0]
            if rows.numel() == 0:
                continue
            found = self._search(key, desc, rays, (lo, hi), rows, samples, refine)
            good = found.ok & (found.cost <= c.max_cost)
            if need_distinct:
                good &= found.distinct >= c.min_distinctiveness
            x[rows], cost[rows], valid[rows] = found.rho, found.cost, good
        valid &= (x >= rho_min) & (x <= rho_max)
        j_x = rays.parallax(torch.where(valid, x, st.mu))[0]
        valid &= j_x > 1e-6
        tau2 = (c.pixel_sigma / torch.clamp(j_x, min=1e-6)) ** 2
        w, h = cam.width, cam.height
        pu, pv, front = rays.project(st.mu[:, None])
        m = self.margin
        visible = (
            front[0, :, 0]
            & (pu[0, :, 0] >= m)
            & (pu[0, :, 0] <= w - 1 - m)
            & (pv[0, :, 0] >= m)
            & (pv[0, :, 0] <= h - 1 - m)
        )

        init = fresh & valid
        upd = ~fresh & valid
        fail = (short | long) & ~fresh & ~valid & visible
        post = gaussian_uniform_update(
            st, torch.where(upd, x, st.mu), torch.where(upd, tau2, st.var), self.rho_range
        )
        voted = outlier_vote(st, fail)
        st.mu = torch.where(init, x, torch.where(upd, post.mu, st.mu))
        st.var = torch.where(init, tau2, torch.where(upd, post.var, st.var))
        st.a = torch.where(init, torch.full_like(st.a, c.init_a), torch.where(upd, post.a, voted.a))
        st.b = torch.where(init, torch.full_like(st.b, c.init_b), torch.where(upd, post.b, voted.b))
        key.updates = key.updates + (init | upd).long()
        key.cost = torch.where(init | upd, cost, key.cost)
        # Outliers: a pixel that keeps failing is reset to "no estimate" (it may be re-seeded).
        drop = (key.updates > 0) & (st.inlier_ratio < c.min_inlier_ratio)
        if bool(drop.any()):
            fresh_state, _, _ = self._fresh_state(int(st.mu.numel()))
            st.mu = torch.where(drop, fresh_state.mu, st.mu)
            st.var = torch.where(drop, fresh_state.var, st.var)
            st.a = torch.where(drop, fresh_state.a, st.a)
            st.b = torch.where(drop, fresh_state.b, st.b)
            key.updates = torch.where(drop, torch.zeros_like(key.updates), key.updates)
