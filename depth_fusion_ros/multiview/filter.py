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
2. **Update** (``filter_frame_update``): cheap tests on every pixel pick those the frame can
   teach something: the gradient along the epipolar line at least ``min_epipolar_gradient``
   (LSD-SLAM), the prior
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
3. **New keyframe** (``filter_new_keyframe``) when the parallax reaches ``keyframe_parallax``,
   the rotation ``keyframe_rotation_deg`` or the visible fraction of the estimates falls below
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
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from ..camera import PinholeCamera
from ..chunking import effective_chunk_elements
from ..geometry import relative_pose, rotation_angle, validate_pose
from ..image_cells import ImageCells
from ..true_indices import true_indices
from .descriptors import patch_reach, stage_descriptors
from .filter_bracket import neighbour_range, neighbour_range_dense
from .filter_config import FilterConfig
from .filter_frame_update import update_frame
from .filter_keyframe import FilterKeyframe
from .filter_new_keyframe import new_keyframe, propagate
from .filter_profile import StageClock
from .filter_propagate import warp_estimates
from .filter_result import FilterResult, assemble_result
from .filter_search import SearchResult, search_interval
from .focal_bias import inverse_depth_bias, remember_update, spaced
from .match_refinement import as_uint8
from .pose_refinement import PoseRefiner
from .semidense import MultiViewConfig
from .views import _as_gray

log = logging.getLogger(__name__)

#: What :meth:`DepthFilter.process` did with a frame.
UPDATED, SKIPPED, KEYFRAME = 'updated', 'skipped', 'keyframe'
#: Frames whose used (refined) pose :meth:`DepthFilter.result` can look up by their told pose:
#: the node reads the frame it just fed, a fixed-lag read a few keyframes back.
USED_POSES_KEPT = 256


@dataclass
class FilterStats:
    """Frames seen, used, skipped, keyframes made, and the switches across a jump (a keyframe
    turned further than ``max_rotation_deg`` from the last: its estimates to confirm again)."""

    frames: int = 0
    updated: int = 0
    skipped: int = 0
    keyframes: int = 0
    jumps: int = 0
    #: Frames whose pose was refined against the keyframe's image, and frames that kept their
    #: told pose because the refinement failed (``filter.refine_poses``).
    refined: int = 0
    kept_told: int = 0


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
        #: How far the focal length may be off (relative), for the published std
        #: (``multiview/focal_bias.py``): ``filter.focal_uncertainty`` until the node or the
        #: evaluation sets what the focal length check verified.
        self.focal_uncertainty = self.config.focal_uncertainty
        self._candidates = dataclasses.replace(
            self.matching,
            max_candidate_fraction=self.config.max_candidate_fraction,
            min_gradient=self.config.min_gradient,
        )
        c = self.config
        self.refiner = (
            PoseRefiner(camera, c.refine_sigma_deg, c.refine_sigma_m, c.refine_corners)
            if c.refine_poses
            else None
        )
        #: Told camera-to-world poses of the last frames (their bytes) -> the poses the filter
        #: used for them: :meth:`result` reads an estimate in a frame by its told pose.
        self._used_poses: OrderedDict[bytes, np.ndarray] = OrderedDict()

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
        told = T_wf
        raw, gray = gray, _as_gray(gray, 'frame image', self.camera)
        image = torch.as_tensor(gray, device=self.device)
        # The refiner's OpenCV tracking takes uint8: the caller's own when it gave uint8.
        gray8 = as_uint8(np.asarray(raw)) if self.refiner is not None else None
        self.stats.frames += 1
        describe = lambda: self._describe(image)  # noqa: E731
        with torch.no_grad():
            if self.key is None:
                self.key = new_keyframe(self, image, describe(), T_wf)
                self.key.first = True
                self.stats.keyframes += 1
                self._used(told, T_wf, gray8)
                return KEYFRAME
            key = self.key
            self._scene = self.scene_depth()
            T_fk, parallax, rotation = self._motion(key, T_wf)
            if self.refiner is not None and (
                parallax >= self.config.min_parallax or rotation >= self.config.keyframe_rotation_deg
            ):
                T_wf = self._refined(gray8, T_wf)
                T_fk, parallax, rotation = self._motion(key, T_wf)
            usable = parallax >= self.config.min_parallax and rotation <= self.config.max_rotation_deg
            # A skipped frame needs no descriptors unless it becomes the keyframe.
            desc = describe() if usable else None
            seen = update_frame(self, key, desc, T_fk) if usable else self._visible_fraction(key, T_fk)
            if usable:
                remember_update(key.update_poses, T_wf)
            switch = (
                parallax >= self.config.keyframe_parallax
                or rotation >= self.config.keyframe_rotation_deg
                or seen < self.config.keyframe_min_visible
            )
            if switch:
                self.key = propagate(self, key, image, describe() if desc is None else desc, T_wf)
                # The carried estimates were measured by the old keyframe's frames.
                self.key.update_poses = list(key.update_poses)
                self.stats.keyframes += 1
                self._used(told, T_wf, gray8)
                return KEYFRAME
        self._used(told, T_wf)
        if usable:
            self.stats.updated += 1
            return UPDATED
        self.stats.skipped += 1
        return SKIPPED

    def _motion(self, key: FilterKeyframe, T_wf: np.ndarray) -> tuple[np.ndarray, float, float]:
        """The keyframe-to-frame transform, its baseline over the scene depth, and its turn (deg)."""
        T_fk = relative_pose(key.pose, T_wf)
        return (
            T_fk,
            float(np.linalg.norm(T_fk[:3, 3])) / self._scene,
            math.degrees(rotation_angle(T_fk[:3, :3])),
        )

    def _refined(self, gray8: np.ndarray, told: np.ndarray) -> np.ndarray:
        """The frame's pose refined against the keyframe's image, or the told one (counted)."""
        refined = self._refining(self.refiner.refine, gray8, told, self._scene)
        if refined is None:
            self.stats.kept_told += 1
            return told
        self.stats.refined += 1
        return refined

    def _used(self, told: np.ndarray, used: np.ndarray, keyframe_gray8: np.ndarray | None = None) -> None:
        """Remember the pose used for a frame told ``told`` (bounded); a new keyframe's image
        and pose go to the refiner."""
        self._used_poses[np.ascontiguousarray(told, dtype=np.float64).tobytes()] = used
        while len(self._used_poses) > USED_POSES_KEPT:
            self._used_poses.popitem(last=False)
        if keyframe_gray8 is not None:
            self._refining(self.refiner.keyframe, keyframe_gray8, used)

    def _refining(self, call: Callable[..., Any], *args: Any) -> Any:
        """A refiner call on the stage clock. A failure (OpenCV, the numbers) is ``None``: the told
        pose for a frame (counted in ``stats.kept_told``), no refinement until the next keyframe
        for a keyframe (its frames counted so)."""
        left = self.clock.switch('pose_refinement')
        try:
            return call(*args)
        except (cv2.error, ValueError, np.linalg.LinAlgError) as exc:
            log.debug('pose refinement failed: %s', exc)
            return None
        finally:
            self.clock.switch(left)

    def used_pose(self, told: np.ndarray) -> np.ndarray:
        """The pose the filter used for the frame told ``told`` (refined, ``filter.refine_poses``);
        ``told`` itself for a frame it has not seen or no longer remembers."""
        return self._used_poses.get(np.ascontiguousarray(told, dtype=np.float64).tobytes(), told)

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
        rows = true_indices(published)
        st = key.state
        mu, var = st.mu[rows], st.var[rows]
        focal_var = self._focal_variance(key, rows, mu)
        if pose is not None:
            pose = self.used_pose(validate_pose(pose, 'result pose'))
        T_tk = None if pose is None else relative_pose(key.pose, pose)
        if T_tk is None or np.allclose(T_tk, np.eye(4), atol=1e-9):
            target = key.flat[rows]
        else:
            warped = warp_estimates(key.us[rows], key.vs[rows], mu, cam.K, T_tk, cam.size, self.rho_range)
            rows = rows[warped.source]
            target, mu, var = warped.target, warped.rho, var[warped.source] * warped.scale**4
            focal_var = focal_var[warped.source] * warped.scale**4
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
            extra_variance=focal_var,
        )

    def _focal_variance(self, key: FilterKeyframe, rows: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        """Per published row, the squared inverse-depth bias a focal length ``focal_uncertainty``
        off would give it under the frames that updated ``key`` (``multiview/focal_bias.py``);
        0 when the uncertainty is 0 or no frame updated the keyframe yet."""
        if self.focal_uncertainty <= 0 or not key.update_poses or rows.numel() == 0:
            return torch.zeros_like(mu)
        poses = [relative_pose(key.pose, T_wf) for T_wf in spaced(key.update_poses)]
        bias = inverse_depth_bias(self.camera.K, key.us[rows], key.vs[rows], mu, poses)
        return (bias * self.focal_uncertainty) ** 2

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
        if self.refiner is not None:
            self.refiner.refocus(camera)
        return True

    def scene_depth(self) -> float:
        """Median depth of the current estimates (m), or ``filter.scene_depth`` before any exists."""
        if self.key is not None:
            has = self.key.updates > 0
            if int(has.sum()) >= 50:
                # Every 4th pixel: a scale for the parallax tests, at a quarter of the sort.
                mu = self.key.state.mu[::4][has[::4]]
                return float(1.0 / _lower_median(mu if mu.numel() > 0 else self.key.state.mu[has]))
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
        return published & self._regions_passing(key, measured, published), None

    def _regions_passing(
        self, key: FilterKeyframe, measured: torch.Tensor, passed: torch.Tensor
    ) -> torch.Tensor:
        """Per estimate: whether its cell of the ``published_fraction_cells`` grid passes the
        minority test (at least ``min_published_fraction`` of the cell's measured estimates
        pass, or none does). Why per cell: a near region that passes whole lifts the
        keyframe's share above the bar while a far one publishes only its noise-selected,
        too-near tail (``FilterConfig.published_fraction_cells``)."""
        c = self.config
        if c.published_fraction_cells <= 0 or c.min_published_fraction <= 0:
            return torch.ones_like(passed)
        cells = ImageCells.across(self.camera.width, self.camera.height, c.published_fraction_cells)
        index = cells.index(key.us, key.vs)
        # Counts by adding the masks, not by counting the masked indices: a masked select and
        # bincount's size read each wait for the device, and the filter is host-bound on a GPU.
        zeros = torch.zeros(cells.count, dtype=torch.float32, device=index.device)
        measured_count = zeros.index_add(0, index, measured.to(torch.float32))
        passed_count = zeros.index_add(0, index, passed.to(torch.float32))
        sliver = (passed_count > 0) & (passed_count < c.min_published_fraction * measured_count)
        return ~sliver[index]

    def _visible_fraction(self, key: FilterKeyframe, T_fk: np.ndarray) -> float:
        """The keyframe-switch test of a skipped frame: the fraction of the estimates that land
        in it (an update answers the same from its own projection, ``update_frame``)."""
        has = true_indices(key.updates > 0)
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

    # --- seams of the steps in filter_frame_update, filter_bracket ----------------------------

    @property
    def search(self) -> Callable[..., SearchResult]:
        """The interval search the updates use (``filter_frame_update.search_rows``): this
        module's ``search_interval``, read at each frame, so the tests can count and shape the
        searches by patching ``filter.search_interval``."""
        return search_interval

    def _neighbour_range(self, key: FilterKeyframe, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``filter_bracket.neighbour_range`` (the tests compare its two paths)."""
        return neighbour_range(self, key, rows)

    def _neighbour_range_dense(
        self, key: FilterKeyframe, rows: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``filter_bracket.neighbour_range_dense`` (the tests compare its two paths)."""
        return neighbour_range_dense(self, key, rows)


def _lower_median(values: torch.Tensor) -> float:
    """``torch.median`` (the lower of the two middle values) of a 1-D tensor; on CPU by numpy's
    partition (a selection, not a sort: 38 against 83 us for this read of 7.5k estimates,
    one thread), the same value."""
    if values.device.type != 'cpu':
        return float(torch.median(values))
    array = values.numpy()
    k = (array.size - 1) // 2
    return float(np.partition(array, k)[k])
