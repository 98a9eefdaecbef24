"""``fusion_node``: single-view + multi-view depth of one keyframe -> fused depth, confidence, cloud.

The single-view and multi-view results of a keyframe arrive on separate topics at different
times (the network and the multi-view estimate run in parallel in other nodes), so the node pairs
them by **exact header stamp**, together with the keyframe's camera_info (and its image, when
it has come, to colour the points). A pairing waits at most ``pair_timeout`` seconds; because every upstream
stream is in stamp order, a pairing that misses a part which its stream has already passed
is hopeless and dropped at once. Both bounds keep memory flat whatever the input. The pairing
is ``map_node``'s too (``nodes/stamp_pairing.py``).

A complete pairing goes to the worker: stage 1 of the point selection (``fusion.stage1``:
the best ``fusion.stage1_fraction`` of the sweep's points by score, every estimate of the
filter (the default method), as multi_view_node announces its method on a latched topic), then the core's
``fuse_keyframe`` (stage 2 RANSAC, the weighted interpolation, fallbacks). The fused depth
(32FC1, metres), its confidence (32FC1) and the keyframe's camera_info are published with
the source header, and optionally a PointCloud2 in the camera frame for RViz.

The fusion's guard (``fusion/guard.py``) judges every keyframe's multi-view evidence and may
step down from the full fusion (fewer points, a smooth scale correction, the single-view
depth with the multi-view scale, or the single-view depth as it is). Its decision, reason,
keyframe confidence and evidence go out as JSON on ``fused/decision`` (std_msgs/String, one
per fused keyframe, published before the depth) and are tallied per decision in the node's
stats (``counts['decision']``); the keyframe confidence also scales ``fused/confidence``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String

from ..camera import PinholeCamera
from ..check_modes import CHECK_MODES
from ..data import messages
from ..fusion import native_halo, neighbour_median
from ..fusion import pipeline as fusion_pipeline
from ..fusion.consistency import CONSISTENCY_PARAMETER_DESCRIPTIONS, ConsistencyConfig
from ..fusion.guard import GUARD_PARAMETER_DESCRIPTIONS, GuardConfig, MultiViewEvidence
from ..fusion.interpolation import MODES as FUSION_MODES
from ..fusion.pipeline import FUSION_PARAMETER_DESCRIPTIONS, FusionConfig, fuse_keyframe
from ..fusion.stream_scale import STREAM_SCALE_PARAMETER_DESCRIPTIONS, StreamScale, StreamScaleConfig
from ..fusion.weights import WEIGHT_SETS
from ..multiview.semidense import MultiViewConfig
from ..multiview.stage1 import METHOD_RULES, STAGE1_RULES, resolve_rule, stage1_mask
from .base import DepthFusionNode
from .console import run_node
from .diagnostics import Requirement
from .fusion_warmup import exit_now_if_compiling, finish_compiling, start_kernels
from .graph_events import EVENT_FUSED, GraphEvents
from .image_input import InputError, depth_from_message
from .params import ParamSpec, build_dataclass, dataclass_specs, torch_device
from .qos import latched_qos
from .stamp_pairing import Pairing, StampPairer

NODE_NAME = 'fusion_node'

TOPIC_SINGLE = 'depth_fusion/single_view/depth'
TOPIC_OUTPUT_KIND = 'depth_fusion/single_view/output_kind'
TOPIC_MV_DEPTH = 'depth_fusion/multi_view/depth'
TOPIC_MV_SCORE = 'depth_fusion/multi_view/score'
#: Optional part: the multi-view depth std (the guard's parallax evidence) when it came first.
TOPIC_MV_DEPTH_STD = 'depth_fusion/multi_view/depth_std'
TOPIC_MV_BIAS_STD = 'depth_fusion/multi_view/bias_std'
TOPIC_MV_METHOD = 'depth_fusion/multi_view/method'
TOPIC_KEYFRAME_IMAGE = 'depth_fusion/keyframe/image'
TOPIC_KEYFRAME_CAMERA_INFO = 'depth_fusion/keyframe/camera_info'
TOPIC_FUSED_DEPTH = 'depth_fusion/fused/depth'
TOPIC_FUSED_CONFIDENCE = 'depth_fusion/fused/confidence'
TOPIC_FUSED_CAMERA_INFO = 'depth_fusion/fused/camera_info'
TOPIC_FUSED_POINTS = 'depth_fusion/fused/points'
TOPIC_FUSED_DECISION = 'depth_fusion/fused/decision'

OUTPUT_KINDS = ('auto', 'metric_depth', 'inverse_depth', 'relative_depth')

#: Ranges / choices of the ``FusionConfig`` fields exposed as ``fusion.*`` parameters (the
#: descriptions come with the core: ``FUSION_PARAMETER_DESCRIPTIONS``).
FUSION_LIMITS: dict[str, Any] = {
    'sigma1': (1e-6, None),
    'sigma2': (0.0, None),
    'sigma3': (0.0, None),
    'structure_scale': (1e-6, None),
    'weights': WEIGHT_SETS,
    'mode': tuple(FUSION_MODES),
    'fast_stride': (1, 64),
    'chunk_elements': (1024, None),
    'ransac_threshold': (1e-9, None),
    'ransac_iterations': (1, 1_000_000),
    'ransac_min_inliers': (2, None),
    'seed': (0, None),
    'max_points': (-1, None),
    'ransac_model': tuple(getattr(fusion_pipeline, 'RANSAC_MODELS', ())),
    'metric_scale_range': (1.0, None),
    'std_half_weight': (0.0, None),
    'agreement_tau': (0.0, None),
    'agreement_sigma': (1e-3, 1000.0),
    'certainty_floor': (0.0, 1.0),
    'certainty_gain': (0.0, 1e6),
}
#: Ranges of the ``guard.*`` parameters (``GuardConfig``).
GUARD_LIMITS: dict[str, Any] = {
    'neighbourhood_px': (1e-3, None),
    'min_neighbours': (1, None),
    'max_neighbours': (1, 10000),
    'local_tolerance': (1e-6, None),
    'max_relative_std': (1e-6, None),
    'single_error_share': (0.0, 1.0),
    'min_precise_fraction': (0.0, 1.0),
    'min_agreement': (0.0, 1.0),
    'max_mv_noise': (1e-6, None),
    'max_point_noise': (1e-6, None),
    'full_fraction': (0.0, 1.0),
    'min_trusted_points': (1, None),
    'min_scale_points': (1, None),
    'min_inlier_ratio': (0.0, 1.0),
    'scale_sigma_px': (1e-3, None),
    'reach': (0.0, None),
    'max_scale_error': (0.0, None),
}
#: Ranges of the ``consistency.*`` parameters (``ConsistencyConfig``, stage 3 of the selection).
CONSISTENCY_LIMITS: dict[str, Any] = {
    'sigma_px': (1e-3, None),
    'tolerance': (1e-6, None),
    'min_support': (0.0, None),
    'iterations': (1, 100),
}
#: Ranges of the ``stream_scale.*`` parameters (``StreamScaleConfig``; ``sample`` stays the core's).
STREAM_SCALE_LIMITS: dict[str, Any] = {
    'mode': CHECK_MODES,
    'window': (1, 1000),
    'min_keyframes': (1, 1000),
    'engage_ratio': (1.0 + 1e-6, None),
    'max_spread': (1e-6, None),
    'min_points': (1, None),
    'min_share': (0.0, 1.0),
    'relative_tolerance': (1e-6, None),
    'max_jump': (0.0, None),
}
#: Set by the node itself (``device``) rather than under ``fusion.*``.
FUSION_SKIP = ('device',)
#: The node runs in real time by default: the fast mode (``fusion.mode: exact`` for the paper's
#: full sum) with compiled kernels (about 4x faster than eager on CPU; compiled once at start-up,
#: eager if no compiler works).
#: The node's fusion: fast mode, compiled, and at most 4096 points of Ω. The fusion costs
#: pixels x |Ω|; the sweep's Ω stays below 4096 at 320x240 (25 % of a 10-14 % density), the
#: filter sends every estimate (6-40k per keyframe on the synthetic and real sequences), and a uniform
#: subsample keeps their spread (rotation stress case: fused MAE 0.334 m capped, 0.333 m all).
FUSION_NODE_DEFAULTS = {'mode': 'fast', 'compile_kernel': True, 'max_points': 4096}

#: Points of Ω a keyframe is fused with while another one waits (``load_max_points``). The
#: fusion costs pixels x |Ω|: half the node's 4096 takes about two thirds of the time (TUM
#: fr1_xyz, fast mode, one thread: a keyframe's median ~53 against ~80 ms, the interpolation
#: 24-38 against 35-61 ms; fused MAE 0.1373 against 0.1360 m, `scripts/diag/profile_fusion.py`).
LOAD_MAX_POINTS = 2048
#: The same while the compiled kernels are still being built (``compile_in_background``): the
#: eager kernel costs ~5.7x the compiled one per pixel-point pair (TUM fr1_xyz keyframes, fast
#: mode, one thread: 625 against 109 ms at 4096 points), so 512 eager points (68 ms) cost less
#: than the compiled 4096. Measured live (2026-11-27, scripts/diag/live_client.py, 7-Scenes at
#: 30 Hz, 2 cores): a stream that began before the 6-8 s compile ran eagerly at 2048 points, fell
#: behind and stayed behind (17-23 of 29 keyframes fused, latency 0.6-0.8 s), while one that began
#: after it fused 29 of 29 at 0.2 s.
WARMING_MAX_POINTS = 512

REQUIRED_PARTS = ('single', 'mv_depth', 'mv_score', 'camera_info')
#: The parts multi_view_node publishes for a keyframe it chose, and for no other image: a
#: single-view depth passed by their streams without any of them was of an image it did not
#: choose (single_view_node on a raw camera), not a lost keyframe (stamp_pairing.py).
KEYFRAME_PARTS = ('mv_depth', 'mv_score', 'camera_info', 'rgb', 'mv_std', 'mv_bias')
PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec('device', 'cpu', 'torch device of the fusion: cpu, cuda, cuda:1, ...', validate=torch_device),
    ParamSpec(
        'single_view_output_kind',
        'auto',
        'what the single-view depth holds; auto: as announced by single_view_node on '
        f'{TOPIC_OUTPUT_KIND} (metric_depth until heard)',
        choices=OUTPUT_KINDS,
    ),
    ParamSpec(
        'pair_timeout',
        10.0,
        'seconds a keyframe waits for its missing single-view / multi-view part before it is dropped',
        0.01,
    ),
    ParamSpec(
        'max_pending_keyframes', 16, 'keyframes waiting for their parts at most (oldest dropped)', 1, 1000
    ),
    ParamSpec(
        'compile_in_background',
        True,
        'with fusion.compile_kernel: fuse with the eager kernels from the start and switch to the compiled '
        'ones once they are built on a background thread (ready in about a second instead of 10+ s); '
        'false: compile in the constructor, before subscribing',
    ),
    ParamSpec(
        'build_kernels_ahead',
        True,
        'with fusion.compile_kernel on the CPU, where no kernels were built ahead of time (depth-fusion '
        'kernels): build them in a separate process at the lowest CPU priority (~45 s of idle CPU), fusing '
        'with the eager kernels meanwhile, then load them; every later start is warm within seconds. false: '
        'compile in this process at every start (torch.compile, 15-25 s on 2 cores, taking CPU and the GIL '
        'from the live graph)',
    ),
    ParamSpec(
        'load_max_points',
        LOAD_MAX_POINTS,
        'under load (another keyframe already waits in the fusion queue when one starts), fuse it with at '
        'most this many points of Omega instead of fusion.max_points, so a node that falls behind a live '
        'camera catches up sooner (counted as reduced_under_load); 0: never (a paced replay sets 0)',
        0,
    ),
    ParamSpec(
        'warming_max_points',
        WARMING_MAX_POINTS,
        'load_max_points while the compiled kernels are still being built (the eager kernel is ~6x slower '
        'per point); the smaller of the two applies; 0: load_max_points alone',
        0,
    ),
    ParamSpec('publish_points', True, f'publish the fused depth as a PointCloud2 on {TOPIC_FUSED_POINTS}'),
    ParamSpec('points_stride', 2, 'keep every n-th pixel in both directions in the point cloud', 1, 64),
    ParamSpec('points_max_depth', 10.0, 'points farther than this (m) are left out of the cloud', 0.0),
    ParamSpec('points_min_confidence', 0.0, 'points whose confidence is below this are left out', 0.0),
    ParamSpec(
        'points_color',
        True,
        'colour the points with the keyframe image when it has arrived (the multi-view node sends it '
        'before its depth, so it nearly always has; a keyframe never waits for it)',
    ),
    ParamSpec(
        'fusion.stage1',
        'auto',
        'stage 1 of the point selection: fraction (the best fusion.stage1_fraction by score, the '
        'paper), all (every multi-view estimate), auto: the rule of the multi-view method announced '
        f'on {TOPIC_MV_METHOD} (sweep: fraction, filter: all; fraction until heard)',
        choices=STAGE1_RULES,
    ),
    ParamSpec(
        'fusion.stage1_fraction',
        MultiViewConfig().select_fraction,
        'stage 1 of the point selection: keep this fraction of the multi-view points, best score first',
        1e-6,
        1.0,
    ),
    *dataclass_specs(
        FusionConfig,
        'fusion',
        FUSION_PARAMETER_DESCRIPTIONS,
        FUSION_LIMITS,
        FUSION_SKIP,
        FUSION_NODE_DEFAULTS,
    ),
    *dataclass_specs(GuardConfig, 'guard', GUARD_PARAMETER_DESCRIPTIONS, GUARD_LIMITS),
    *dataclass_specs(
        ConsistencyConfig, 'consistency', CONSISTENCY_PARAMETER_DESCRIPTIONS, CONSISTENCY_LIMITS
    ),
    *dataclass_specs(
        StreamScaleConfig,
        'stream_scale',
        STREAM_SCALE_PARAMETER_DESCRIPTIONS,
        STREAM_SCALE_LIMITS,
        skip=('sample',),
    ),
)


@dataclass
class _FusionJob:
    pairing: Pairing
    received_at: float


def under_load(
    config: FusionConfig, waiting: int, load_max_points: int, warming_max_points: int = 0
) -> tuple[FusionConfig, bool]:
    """The config a keyframe is fused with: ``config``, or with at most ``load_max_points``
    points of Ω when ``waiting`` keyframes already queue behind it (and that is fewer than
    ``config.max_points``). Why: a live camera does not wait, and a node that keeps its full
    cost while behind drops every keyframe the queue cannot hold; a cheaper fusion of each
    (about 1 % more error at half the points) lets it catch up. ``warming_max_points`` (> 0
    while the eager kernels stand in for the compiling ones) lowers the cap further. Returns
    whether it reduced.
    """
    if load_max_points <= 0 or waiting <= 0:
        return config, False
    if warming_max_points > 0:
        load_max_points = min(load_max_points, warming_max_points)
    if config.max_points is not None and config.max_points <= load_max_points:
        return config, False
    return dataclasses.replace(config, max_points=load_max_points), True


class FusionNode(DepthFusionNode):
    """Pairs keyframe results by stamp and fuses them on a worker thread."""

    def __init__(self, node_name: str = NODE_NAME, own_process: bool = False, **kwargs: Any) -> None:
        super().__init__(node_name, PARAMETERS, **kwargs)
        self._own_process = own_process
        p = self.params
        self.config = build_dataclass(FusionConfig, p, 'fusion', device=str(p['device']))
        self.guard_config = build_dataclass(GuardConfig, p, 'guard')
        self.consistency_config = build_dataclass(ConsistencyConfig, p, 'consistency')
        #: The single view's scale against the points over the stream (metric sources).
        self.stream_scale = StreamScale(build_dataclass(StreamScaleConfig, p, 'stream_scale'))
        self.announced_kind: str | None = None
        self.announced_method: str | None = None
        self.required = REQUIRED_PARTS
        # The keyframe image colours the cloud and places the points of a silhouette's halo.
        self.want_rgb = bool(p['publish_points'] and p['points_color']) or self.config.halo_min_step > 0
        self.pairer = StampPairer(
            REQUIRED_PARTS,
            ('rgb', 'mv_std', 'mv_bias'),
            timeout=float(p['pair_timeout']),
            max_pending=int(p['max_pending_keyframes']),
            on_complete=lambda pairing: self.worker.submit(_FusionJob(pairing, time.monotonic())),
            on_drop=self.stats.dropped,
            restart_after=float(p['stream_restart_jump']),
            on_restart=lambda part, stamp_ns: self.note_stream_restart(
                part, stamp_ns, 'the keyframes of the previous one still waiting time out'
            ),
            on_dropped_keyframe=lambda stamp_ns, reason: self.events.dropped(stamp_ns, reason),
            keyframe_parts=KEYFRAME_PARTS,
        )

        self._depth_pub = self.create_publisher(Image, TOPIC_FUSED_DEPTH, self.output_qos)
        self._confidence_pub = self.create_publisher(Image, TOPIC_FUSED_CONFIDENCE, self.output_qos)
        self._info_pub = self.create_publisher(CameraInfo, TOPIC_FUSED_CAMERA_INFO, self.output_qos)
        self._decision_pub = self.create_publisher(String, TOPIC_FUSED_DECISION, self.output_qos)
        self._points_pub = (
            self.create_publisher(PointCloud2, TOPIC_FUSED_POINTS, self.output_qos)
            if p['publish_points']
            else None
        )
        self.events = GraphEvents(self)
        #: What the worker fuses with: eager until compiled kernels are ready (see fusion_warmup).
        self.active_config = start_kernels(
            self, self.config, bool(p['compile_in_background']), bool(p['build_kernels_ahead'])
        )
        self.worker = self.make_worker(
            'fusion', self._process, on_lost=lambda job, why: self.events.dropped(job.pairing.stamp_ns, why)
        )
        q = self.input_qos
        self.subscribe(String, TOPIC_OUTPUT_KIND, self._on_output_kind, latched_qos())
        self.subscribe(String, TOPIC_MV_METHOD, self._on_method, latched_qos())
        self.subscribe(CameraInfo, TOPIC_KEYFRAME_CAMERA_INFO, self._on_camera_info, q)
        self.subscribe(Image, TOPIC_KEYFRAME_IMAGE, self._on_keyframe_image, q)
        self.subscribe(Image, TOPIC_MV_DEPTH, lambda m: self._on_depth(m, 'mv_depth'), q)
        self.subscribe(Image, TOPIC_MV_SCORE, lambda m: self._on_depth(m, 'mv_score'), q)
        self.subscribe(Image, TOPIC_MV_DEPTH_STD, lambda m: self._on_depth(m, 'mv_std'), q)
        self.subscribe(Image, TOPIC_MV_BIAS_STD, lambda m: self._on_depth(m, 'mv_bias'), q)
        self.subscribe(Image, TOPIC_SINGLE, lambda m: self._on_depth(m, 'single'), q)
        self.create_wall_timer(min(0.5, float(p['pair_timeout']) / 2), self._expire)
        self.get_logger().info(
            f'fusion ({self.config.mode} mode) on {p["device"]}: {self.resolve_topic_name(TOPIC_SINGLE)} + '
            f'{self.resolve_topic_name(TOPIC_MV_DEPTH)} -> {self.resolve_topic_name(TOPIC_FUSED_DEPTH)}'
        )
        if str(p['device']) == 'cpu':
            neighbour_median.prepare()  # the guard's native kernel: built here, not at the first keyframe
            native_halo.prepare()  # the halo test's
        self.events.ready(warm=self.kernels_ready.is_set())  # not warm while compiling in the background

    # --- callbacks: collect parts by stamp ------------------------------------------------------------

    def _on_output_kind(self, msg: String) -> None:
        if msg.data not in OUTPUT_KINDS[1:]:
            self.stats.dropped('bad_output_kind', f'single-view output kind {msg.data!r} is unknown')
            return
        self.announced_kind = msg.data

    def _on_method(self, msg: String) -> None:
        if msg.data not in METHOD_RULES:
            self.stats.dropped('bad_multi_view_method', f'multi-view method {msg.data!r} is unknown')
            return
        self.announced_method = msg.data

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.stats.received('camera_info')
        try:
            calib = messages.camera_info_to_calibration(msg)
        except ValueError as exc:
            self.stats.dropped('bad_camera_info', f'keyframe camera_info: {exc}')
            return
        if calib.is_distorted:
            self.stats.dropped(
                'bad_camera_info', 'keyframe camera_info has distortion: expected the working grid'
            )
            return
        self._add_part(msg, 'camera_info', (calib.camera, msg))

    def _on_keyframe_image(self, msg: Image) -> None:
        if not self.want_rgb:
            return
        self.stats.received('keyframe_image')
        try:
            rgb = messages.image_to_rgb(msg)
        except ValueError as exc:
            self.stats.dropped('bad_encoding', f'keyframe image: {exc}')
            return
        self._add_part(msg, 'rgb', rgb)

    def _on_depth(self, msg: Image, part: str) -> None:
        self.stats.received(part)
        try:
            depth = depth_from_message(msg, part)
        except InputError as exc:
            self.stats.dropped(exc.reason, str(exc))
            return
        self._add_part(msg, part, depth)

    @property
    def pending(self) -> dict[int, Pairing]:
        """Keyframes waiting for a part, by stamp (the pairer's)."""
        return self.pairer.pending

    def _add_part(self, msg: Any, part: str, value: Any) -> None:
        self.pairer.add(msg.header, part, value)

    def _expire(self) -> None:
        self.pairer.expire(time.monotonic())

    def diagnostic_requirements(self) -> list[Requirement]:
        """Each half of a keyframe needs the other (a dead single-view or multi-view node)."""
        single, mv = self.resolve_topic_name(TOPIC_SINGLE), self.resolve_topic_name(TOPIC_MV_DEPTH)
        return [Requirement('single', 'mv_depth', single), Requirement('mv_depth', 'single', mv)]

    def diagnostic_extra(self) -> dict[str, Any]:
        return {
            'pending keyframes': len(self.pending),
            'single-view output kind': self.output_kind,
            'single-view depths of images not chosen as keyframes': self.pairer.not_keyframes,
        }

    def destroy_node(self) -> None:
        # Composed, this process lives on (and must not exit mid-compile); a node process
        # exits at once instead (main).
        finish_compiling(self, 0.0 if self._own_process else 120.0)
        super().destroy_node()

    # --- worker ---------------------------------------------------------------------------------------

    @property
    def output_kind(self) -> str:
        kind = str(self.params['single_view_output_kind'])
        if kind == 'auto':
            return self.announced_kind or 'metric_depth'
        return kind

    def _process(self, job: _FusionJob) -> None:
        parts = job.pairing.parts
        header = job.pairing.header
        camera, info_msg = parts['camera_info']
        try:
            single, mv_depth, mv_score = _checked_inputs(parts, camera)
        except InputError as exc:
            self.stats.dropped(exc.reason, f'keyframe {messages.ns_to_sec(job.pairing.stamp_ns):.3f}: {exc}')
            self.events.dropped(job.pairing.stamp_ns, exc.reason)
            return
        rule = resolve_rule(str(self.params['fusion.stage1']), self.announced_method)
        stage1 = stage1_mask(mv_depth, mv_score, rule, float(self.params['fusion.stage1_fraction']))
        stamp = messages.ns_to_sec(job.pairing.stamp_ns)
        waiting = self.worker.pending
        warming = 0 if self.kernels_ready.is_set() else int(self.params['warming_max_points'])
        config, reduced = under_load(
            self.active_config, waiting, int(self.params['load_max_points']), warming
        )
        if reduced:
            self.stats.noted(
                'reduced_under_load',
                f'keyframe {stamp:.3f}: fused with at most {config.max_points} points, '
                f'{waiting} more waiting (load_max_points{", kernels still compiling" if warming else ""})',
            )
        result = fuse_keyframe(
            single,
            mv_depth,
            stage1,
            config,
            output_kind=self.output_kind,
            guard_config=self.guard_config,
            # the parallax evidence evaluate gives the guard, when the optional std parts came
            evidence=MultiViewEvidence.from_depth_std(
                mv_depth,
                _same_shape(parts.get('mv_std'), mv_depth),
                bias_std=_same_shape(parts.get('mv_bias'), mv_depth),
            ),
            consistency_config=self.consistency_config,
            image=self._halo_image(parts.get('rgb'), single.shape, stamp),
            stream_scale=self.stream_scale,
            stamp=job.pairing.stamp_ns,
        )
        if result.stream_scale_found:
            self.stats.noted('stream_scale', f'keyframe {stamp:.3f}: {self.stream_scale.describe()}')
        explained = result.evidence.get('edge_explained', 0.0)
        if explained > 0:  # fusion/edge_points.py: counted, so a summary says how often
            self.stats.noted(
                'edge_points',
                f"keyframe {stamp:.3f}: its points lie on the single view's depth edges "
                f"({result.evidence['edge_ratio']:.1f}x the pixels' rate); {explained:.0%} of them "
                "agree with it within its edges' blur and corrected nothing",
            )
        if result.withheld:
            self.stats.noted(
                'withheld', f'keyframe {stamp:.3f}: no depth published ({result.decision_reason})'
            )
        if result.fallback:
            self.stats.noted(
                f'fallback_{result.fallback}', f'keyframe {stamp:.3f}: fell back ({result.fallback})'
            )
        elif result.decision not in ('full', 'fewer_points'):
            self.stats.noted(
                f'guard_{result.decision}',
                f'keyframe {stamp:.3f}: {result.decision} ({result.decision_reason})',
            )
        if result.n_nonpositive:
            self.stats.noted(
                'nonpositive_aligned',
                f'keyframe {stamp:.3f}: {result.n_nonpositive} pixels of '
                f'the {self.output_kind} source aligned to a non-positive depth (published as NaN)',
            )
        self.stats.count('decision', result.decision)
        self._decision_pub.publish(String(data=decision_json(result, job.pairing.stamp_ns, reduced)))
        kind = messages.RCLPY
        self._depth_pub.publish(messages.depth_image_msg(result.depth, header, kind=kind))
        confidence = np.asarray(result.confidence, dtype=np.float32)
        self._confidence_pub.publish(messages.image_msg(confidence, '32FC1', header, kind=kind))
        self._info_pub.publish(info_msg)
        if self._points_pub is not None:
            self._points_pub.publish(self._cloud(result.depth, confidence, camera, parts.get('rgb'), header))
        self.stats.published('fused')
        self.events.event(job.pairing.stamp_ns, EVENT_FUSED)
        self.stats.processed(time.monotonic() - job.received_at)

    def _halo_image(self, rgb: np.ndarray | None, shape: tuple[int, ...], stamp: float) -> np.ndarray | None:
        """The keyframe image for the fusion's halo test, or None (counted) when it did not come
        in time or is not on the depth's grid: the keyframe is then fused without the test."""
        if self.config.halo_min_step <= 0:
            return None
        if rgb is None or rgb.shape[:2] != tuple(shape):
            why = 'did not come' if rgb is None else f'is {rgb.shape[1]}x{rgb.shape[0]}, off the depth grid'
            self.stats.noted(
                'halo_unchecked', f'keyframe {stamp:.3f}: its image {why}; fused without the halo test'
            )
            return None
        return rgb

    def _cloud(
        self,
        depth: np.ndarray,
        confidence: np.ndarray,
        camera: PinholeCamera,
        rgb: np.ndarray | None,
        header: Any,
    ) -> PointCloud2:
        """The fused depth as camera-frame points (every ``points_stride``-th pixel, filtered)."""
        stride = int(self.params['points_stride'])
        points = camera.backproject(depth, stride).reshape(-1, 3)
        z = points[:, 2]
        with np.errstate(invalid='ignore'):
            keep = np.isfinite(z) & (z > 0) & (z <= float(self.params['points_max_depth']))
            keep &= confidence[::stride, ::stride].ravel() >= float(self.params['points_min_confidence'])
        colours = None
        if rgb is not None and rgb.shape[:2] == depth.shape:
            colours = rgb[::stride, ::stride].reshape(-1, 3)[keep]
        return messages.pointcloud2_msg(points[keep], header, kind=messages.RCLPY, rgb=colours)


def _same_shape(part: np.ndarray | None, like: np.ndarray) -> np.ndarray | None:
    """An optional image part, or None when it is missing or of another size."""
    return part if part is not None and part.shape == like.shape else None


def decision_json(result: Any, stamp_ns: int, reduced_under_load: bool = False) -> str:
    """The guard's verdict for one keyframe as one JSON line (``fused/decision``), and whether
    the keyframe was fused with ``load_max_points`` points because another one waited.

    ``stamp`` is in seconds, for reading; ``stamp_ns`` is the keyframe's header stamp exactly
    (a float of seconds holds a 2026 stamp to about 240 ns only), which single_view_node's
    adaptation matches it by."""
    evidence = {k: (round(v, 4) if np.isfinite(v) else None) for k, v in result.evidence.items()}
    return json.dumps(
        {
            'stamp': messages.ns_to_sec(stamp_ns),
            'stamp_ns': int(stamp_ns),
            'decision': result.decision,
            'reason': result.decision_reason,
            'confidence': round(float(result.keyframe_confidence), 4),
            'n_stage1': int(result.n_stage1),
            'n_points': int(result.n_omega),
            'fallback': result.fallback,
            'withheld': bool(result.withheld),
            'reduced_under_load': bool(reduced_under_load),
            'evidence': evidence,
        }
    )


def _checked_inputs(
    parts: dict[str, Any], camera: PinholeCamera
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Single-view depth, multi-view depth and score, all on the camera's grid, or ``InputError``."""
    shape = (camera.height, camera.width)
    single, mv_depth, mv_score = parts['single'], parts['mv_depth'], parts['mv_score']
    for name, arr in (
        ('single-view depth', single),
        ('multi-view depth', mv_depth),
        ('multi-view score', mv_score),
    ):
        if arr.shape != shape:
            raise InputError(
                'size_mismatch',
                f'{name} is {arr.shape[1]}x{arr.shape[0]}, camera_info says {shape[1]}x{shape[0]}',
            )
    return single, mv_depth, mv_score


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point: ``fusion_node --ros-args --params-file config/depth_fusion.yaml``."""
    return exit_now_if_compiling(run_node(lambda: FusionNode(own_process=True), args))


if __name__ == '__main__':
    raise SystemExit(main())
