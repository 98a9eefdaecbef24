"""The single-view node's online adaptation: parameters, training-signal topics, save service.

Thin glue between ROS and ``depth_fusion_ros.adaptation``: it declares the ``adapt`` and
``adaptation.*`` parameters, subscribes to the multi-view depth and score and to the keyframe
pose, assembles each keyframe's sample (``KeyframeAssembler``), hands it to the training
thread (``OnlineAdaptation``) and serves ``~/save_model``. Without a keyframe pose topic it
adapts with the sparse multi-view term only, and says so once.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import Image
from std_msgs.msg import String

from ..adaptation.adapter import Adapter, UpdateReport
from ..adaptation.config import AdaptConfig
from ..adaptation.fusion_trust import trust_from_json
from ..adaptation.keyframes import KeyframeAssembler
from ..adaptation.online import OnlineAdaptation, WeightSlot
from ..adaptation.remote_adapter import RemoteAdapter
from ..adaptation.sample import AdaptSample
from ..data import messages
from ..geometry import rotation_angle
from ..multiview.frame_fit import MIN_TURN_DEG
from ..ros_home import expand_ros_home
from .corrected_path import path_poses
from .image_input import InputError, WorkingImage, depth_from_message, header_stamp_ns, pose_from_message
from .params import ParamSpec, build_dataclass, dataclass_specs
from .posing import TOPIC_POSING_TRANSFORM, TOPIC_REPOSED_KEYFRAMES, PosingLog, posing_qos

TOPIC_MV_DEPTH = 'depth_fusion/multi_view/depth'
TOPIC_MV_SCORE = 'depth_fusion/multi_view/score'
TOPIC_MV_DEPTH_STD = 'depth_fusion/multi_view/depth_std'
#: fusion_node's verdict per keyframe (std_msgs/String JSON): a keyframe whose points it trusted
#: none of is not trained on (adaptation/fusion_trust.py).
TOPIC_FUSED_DECISION = 'depth_fusion/fused/decision'
#: Published by multi_view_node for every keyframe (PoseStamped, world frame, keyframe stamp).
TOPIC_KEYFRAME_POSE = 'depth_fusion/keyframe/pose'
SERVICE_SAVE = '~/save_model'
#: A turn of multi_view_node's camera at least this large (deg) is a whole frame's (its mount
#: check fits turns of up to 15 deg, its frame check finds larger ones: multiview/frame_fit.py)
#: and starts the adaptation over: the points trained on before came from motion that wrong.
RESTART_TURN_DEG = MIN_TURN_DEG
ADAPT_CHOICES = ('auto', 'true', 'false')
#: Under ``$ROS_HOME`` (``~/.ros`` when unset; ros_home.py), expanded when it is written.
DEFAULT_CHECKPOINT = '$ROS_HOME/depth_fusion_ros/single_view_adapted.pt'

ADAPT_LIMITS: dict[str, Any] = {
    'lr': (1e-9, 1.0),
    'scale_lr': (0.0, 1.0),
    'steps_per_keyframe': (1, 1000),
    'buffer_size': (1, 10000),
    'replay_per_step': (0, 64),
    'steps_when_behind': (1, 1000),
    'photometric_window': (0.05, 1.0),
    'sparse_weight': (0.0, None),
    'photometric_weight': (0.0, None),
    'smoothness_weight': (0.0, None),
    'anchor_weight': (0.0, None),
    'ssim_alpha': (0.0, 1.0),
    'select_fraction': (1e-6, 1.0),
    'holdout_fraction': (0.0, 0.9),
    'min_points': (0, None),
    'min_coverage': (0.0, 1.0),
    'start_coverage': (0.0, 1.0),
    'max_relative_std': (1e-6, None),
    'min_precise_fraction': (0.0, 1.0),
    'guard_keyframes': (0, 1000),
    'guard_tolerance': (0.0, None),
    'guard_z': (0.0, None),
    'grad_clip': (0.0, None),
    'seed': (0, None),
}

ADAPTATION_PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec(
        'adapt',
        'auto',
        "online self-supervised adaptation of the network to the scene: 'auto' = on for the project's "
        'own networks (the shipped model, checkpoints of depth-fusion train/adapt), off for TorchScript '
        "models; 'true' (an error for a model that cannot adapt) or 'false' (the network as loaded)",
        choices=ADAPT_CHOICES,
    ),
    ParamSpec(
        'adaptation.checkpoint',
        DEFAULT_CHECKPOINT,
        'where ~/save_model and shutdown write the adapted weights, a checkpoint that model: loads '
        'as it is written ($ROS_HOME: ~/.ros when unset); shutdown writes only when an update was '
        "accepted; '' = nothing is written at shutdown",
    ),
    ParamSpec(
        'adaptation.queue_size',
        2,
        'keyframes waiting for the training thread; when it falls behind the oldest is dropped (counted)',
        1,
        100,
    ),
    ParamSpec(
        'adaptation.process',
        True,
        'train in a process of its own (true) or on a thread of this one (false): in a process the '
        "training's Python work never holds this process's GIL, so a niced trainer cannot hold up "
        'inference or, composed, the other nodes',
    ),
    ParamSpec(
        'adaptation.nice',
        10,
        'scheduling niceness of the training process or thread (Linux): training then uses the CPU that '
        'inference, multi-view and fusion leave idle instead of delaying them; 0 = the same priority as '
        'inference',
        0,
        19,
    ),
    ParamSpec(
        'adaptation.idle_policy',
        True,
        'Linux: run the training process under SCHED_IDLE, only on a core no node wants, given up '
        "at once when a node's thread wakes (a niceness alone lets it keep the core for its time slice "
        'under the EEVDF scheduler of Linux 6.6+); the training process only: with adaptation.process '
        'false the thread keeps adaptation.nice (a warning says so)',
    ),
    ParamSpec(
        'adaptation.neighbours',
        2,
        'previous posed keyframes warped into each keyframe for the photometric term (0: sparse term only)',
        0,
        8,
    ),
    ParamSpec(
        'adaptation.min_baseline',
        0.02,
        'a previous keyframe is a photometric neighbour only if its camera is at least this far (m)',
        0.0,
    ),
    *dataclass_specs(AdaptConfig, 'adaptation', {}, ADAPT_LIMITS),
)


def is_own_network(spec: str) -> bool:
    """True for networks the adapter can train: the shipped model and our checkpoints."""
    from ..singleview.checkpoint import is_exported_model
    from ..singleview.predictor import model_path

    if spec == 'default':
        return True
    path = model_path(spec)
    return path.is_file() and not is_exported_model(path)


def adaptation_wanted(params: dict[str, Any]) -> bool:
    """Resolve ``adapt`` (auto / true / false) for ``model``; ``true`` on a model that cannot
    adapt is a start-up error naming it."""
    mode, model = str(params['adapt']), str(params['model'])
    if mode == 'false':
        return False
    own = is_own_network(model)
    if mode == 'true' and not own:
        raise ValueError(
            f"single_view_node: adapt is 'true' but model {model!r} cannot be adapted (only the shipped "
            'model and checkpoints of depth-fusion train/adapt can; exported ONNX / .pt2 / TorchScript '
            "cannot): set adapt: 'false'"
        )
    return own


class NodeAdaptation:
    """Everything the node does for adaptation, given the node and its loaded predictor."""

    def __init__(self, node: Any, predictor: Any) -> None:
        p = node.params
        self.node = node
        self.config = build_dataclass(AdaptConfig, p, 'adaptation')
        self.config.validate()
        given = str(p['adaptation.checkpoint'])
        #: Where the adapted weights go (``$ROS_HOME`` expanded once), ``None`` for ''.
        self.checkpoint: Path | None = expand_ros_home(given) if given else None
        nice = int(p['adaptation.nice'])
        in_process, idle = bool(p['adaptation.process']), bool(p['adaptation.idle_policy'])
        if idle and not in_process:
            idle = False
            node.get_logger().warning(
                'adaptation.idle_policy applies to the training process only (adaptation.process is '
                "false): a SCHED_IDLE thread would hold this node's GIL while it waits for a core; the "
                f'thread trains at nice +{nice}'
            )
        #: The training process (``adaptation.process``), else None: training on the thread.
        self.remote = (
            RemoteAdapter(str(p['model']), self.config, str(p['device']), nice=nice, idle=idle)
            if in_process
            else None
        )
        self.adapter = self.remote or Adapter.from_spec(str(p['model']), self.config, str(p['device']))
        self.slot = WeightSlot(predictor)
        # Before the training thread starts: its warm callback reads them, and a training thread
        # (adaptation.process false) can be warm before this constructor has returned.
        self._lock = threading.Lock()
        self._stopping = False
        self.online = OnlineAdaptation(
            self.adapter,
            self.slot,
            int(p['adaptation.queue_size']),
            on_report=self._on_report,
            on_warm=self._on_warm,
            nice=0 if self.remote else nice,  # that thread only waits for the process, niced itself
        )
        self.assembler = KeyframeAssembler(
            select_fraction=self.config.select_fraction,
            holdout_fraction=self.config.holdout_fraction,
            seed=self.config.seed,
            neighbours=int(p['adaptation.neighbours']),
            min_baseline=float(p['adaptation.min_baseline']),
            max_relative_std=self.config.max_relative_std,
        )
        self._uncalibrated: set[int] = set()
        self._said_sparse_only = False
        q = node.input_qos
        node.subscribe(Image, TOPIC_MV_DEPTH, lambda m: self._on_depth(m, 'depth'), q)
        node.subscribe(Image, TOPIC_MV_SCORE, lambda m: self._on_depth(m, 'score'), q)
        node.subscribe(Image, TOPIC_MV_DEPTH_STD, lambda m: self._on_depth(m, 'std'), q)
        node.subscribe(PoseStamped, TOPIC_KEYFRAME_POSE, self._on_pose, q)
        if self.config.follow_fusion_guard:
            node.subscribe(String, TOPIC_FUSED_DECISION, self._on_decision, q)
        #: How multi_view_node posed each keyframe: a mount turn it takes re-poses the photometric
        #: neighbours (nodes/posing.py).
        self.posings = PosingLog()
        node.subscribe(TransformStamped, TOPIC_POSING_TRANSFORM, self._on_posing, posing_qos())
        node.subscribe(PathMsg, TOPIC_REPOSED_KEYFRAMES, self._on_reposed, posing_qos())
        from std_srvs.srv import Trigger

        self.service = node.create_service(Trigger, SERVICE_SAVE, self._on_save)
        where = f'in training process {self.remote.pid}' if self.remote else 'on a training thread'
        where += f' at nice +{nice}' + (' under SCHED_IDLE' if idle else '')
        node.get_logger().info(
            f'adapting {self.adapter.name} online {where}: lr {self.config.lr:g}, '
            f'{self.config.steps_per_keyframe} steps/keyframe, replay {self.config.replay_per_step} of '
            f'{self.config.buffer_size} ({self.config.steps_when_behind} steps while behind), windows of '
            f'{self.config.photometric_window:g} of each side; '
            f'signals {node.resolve_topic_name(TOPIC_MV_DEPTH)}, '
            f'{node.resolve_topic_name(TOPIC_KEYFRAME_POSE)}; checkpoint {self.checkpoint or "(none)"}'
        )

    # --- parts of a keyframe --------------------------------------------------------------------

    def on_keyframe_image(self, image: WorkingImage, calibrated: bool) -> None:
        if not calibrated:
            self._uncalibrated.add(image.stamp_ns)
        self._add(image.stamp_ns, 'rgb', image.rgb, image.camera)

    def _on_depth(self, msg: Image, part: str) -> None:
        self.node.stats.received(f'mv_{part}')
        try:
            value = depth_from_message(msg, f'multi-view {part}')
        except InputError as exc:
            self.node.stats.dropped(exc.reason, str(exc))
            return
        self._add(header_stamp_ns(msg), part, value)

    def _on_decision(self, msg: String) -> None:
        """fusion_node's verdict on a keyframe: the reason its guard trusted none of the points
        ('' when it did) and the factor it moved them by (the share of their scale it took)
        become the keyframe's ``trust`` part."""
        self.node.stats.received('fused_decision')
        try:
            stamp_ns, trust = trust_from_json(msg.data)
        except ValueError as exc:
            self.node.stats.dropped('bad_decision', f'fused/decision: {exc}')
            return
        self._add(stamp_ns, 'trust', trust)

    def _on_pose(self, msg: PoseStamped) -> None:
        self.node.stats.received('keyframe_pose')
        try:
            pose = pose_from_message(msg)
        except InputError as exc:
            self.node.stats.dropped(exc.reason, str(exc))
            return
        stamp_ns = header_stamp_ns(msg)
        with self._lock:  # posed before a posing change heard already (in flight): as it says
            pose = self.posings.arriving(stamp_ns, pose)
        self._add(stamp_ns, 'pose', pose)

    def _on_posing(self, msg: Any) -> None:
        """multi_view_node's ``camera_from_pose_frame``; another one than the last (its mount
        check turned the camera) re-poses the neighbours and waiting poses (``repose``). A turn
        of a whole frame (:data:`RESTART_TURN_DEG` or more) also starts the training over
        (:meth:`_restart`). Counted once taken (or dropped): a count read elsewhere never runs
        ahead of what is held."""
        try:
            with self._lock:
                turn = self.posings.on_transform(msg)
                if turn is None:
                    return
                moved = self.assembler.repose(turn)
        except ValueError as exc:  # a transform that is not rigid
            self.node.stats.dropped('bad_posing', f'posing from multi_view_node unusable: {exc}')
            return
        finally:
            self.node.stats.received('posing')
        angle = float(np.degrees(rotation_angle(turn[:3, :3])))
        self.node.get_logger().info(
            f'adaptation: multi_view_node turned the camera by {angle:.1f} deg (mount check): {moved} kept '
            'poses re-posed'
        )
        if angle >= RESTART_TURN_DEG:
            self._restart(messages.stamp_to_ns(msg.header.stamp), angle)

    def _restart(self, from_ns: int, angle: float) -> None:
        """Start the training over from the loaded weights: the multi-view points of every
        keyframe before ``from_ns`` were triangulated with motion turned by ``angle`` deg, and
        the guard, which holds out points of the same poses, could not see it."""
        reason = (
            f'multi_view_node turned the camera by {angle:.0f} deg (the told poses were of another frame): '
            'the keyframes trained on before were triangulated with the wrong motion'
        )
        let_go = self.online.restart(from_ns, reason)
        self.node.stats.noted(
            'adapt_restarted',
            f'adaptation starts over from the loaded weights: {reason}; {let_go} queued keyframes let go, '
            'none before the turn is trained on',
        )

    def _on_reposed(self, msg: Any) -> None:
        """multi_view_node's ``reposed_keyframes``: the keyframes posed before its time offset
        correction, read again at the corrected offset; the neighbours and waiting poses take
        them, and keyframes whose pose has not come yet take them when it does."""
        self.node.stats.received('reposed_keyframes')
        stamps, read, bad = path_poses(msg)
        if bad:
            self.node.stats.dropped('bad_pose', f'reposed keyframes: {bad} of {len(msg.poses)} unusable')
        with self._lock:
            poses = self.posings.reread_in_latest(messages.stamp_to_ns(msg.header.stamp), stamps, read)
            held = self.assembler.reread(poses)
            self.posings.hold({stamp: T for stamp, T in poses.items() if stamp not in held})
        self.node.get_logger().info(
            f'adaptation: multi_view_node corrected its pose time offset: {len(held)} kept poses re-read '
            'at it'
        )

    def _add(self, stamp_ns: int, part: str, value: Any, camera: Any = None) -> None:
        with self._lock:
            samples = self.assembler.add(stamp_ns, part, value, camera)
        for sample in samples:
            self._submit(sample)

    def _submit(self, sample: AdaptSample) -> None:
        if sample.key in self._uncalibrated:
            self._uncalibrated.discard(sample.key)
            sample.pose, sample.neighbours = None, []  # no intrinsics: no photometric term
        if not sample.has_photometric and not self._said_sparse_only:
            self._said_sparse_only = True
            self.node.get_logger().info(
                f'adaptation: keyframe without pose, camera_info or posed neighbour on '
                f'{self.node.resolve_topic_name(TOPIC_KEYFRAME_POSE)}: adapting with the sparse '
                'multi-view term only while this lasts (said once)'
            )
        if not self.online.submit(sample):
            # A note, not a drop: the keyframe's depth was published; only its training is
            # skipped (as a drop it counted in the node's drop share: 19 of 145 inputs, 13 %,
            # over the 10 % that turns /diagnostics WARN, in a live run with every depth out).
            self.node.stats.noted('adapt_queue_full', 'training fell behind: oldest keyframe not trained on')

    # --- results --------------------------------------------------------------------------------

    def _on_warm(self) -> None:
        """The node's warm line once training can take keyframes (graph_events): a replay waits
        for it (``bag_replayer.wait_warm``), so that a bag is trained on from its first keyframe
        instead of after the 4-8 s a training process takes to import torch and build its
        optimiser on a busy 2-core machine. A live stream is not held up: the node was ready
        (inference) before."""
        if self._stopping:
            return
        if self.remote is None:
            what = 'adaptation: training thread ready'
        elif self.remote.ready:
            what = f'adaptation: training process {self.remote.pid} ready'
        else:  # the error was logged; a replay must not wait for a training that will not come
            what = 'adaptation: no training process (see the error above); warm without it'
        self.node.events.warm(what)

    def _on_report(self, report: UpdateReport) -> None:
        stats = self.node.stats
        if report.status in ('updated', 'restarted'):  # new weights swapped in either way
            stats.published('adapted_weights')
        elif report.status == 'rolled_back':
            g = report.guard
            stats.noted(
                'adapt_rollback',
                f'keyframe {report.key} update rolled back: held-out error {g.before:.4f} -> {g.after:.4f}',
            )
        else:
            stats.noted('adapt_skipped', f'keyframe {report.key} not trained on: {report.reason}')

    def save(self) -> Path:
        if not self.checkpoint:
            raise ValueError("adaptation.checkpoint is '' : no path to save the adapted model to")
        return self.online.save(self.checkpoint)

    def _on_save(self, request: Any, response: Any) -> Any:
        try:
            path = self.save()
        except (OSError, ValueError) as exc:
            response.success, response.message = False, f'not saved: {exc}'
        else:
            response.success = True
            response.message = f'saved adapted weights (version {self.slot.version}) to {path}'
            self.node.get_logger().info(response.message)
        return response

    def shutdown(self) -> None:
        """Stop the training thread, then write the checkpoint (when a path is set)."""
        self._stopping = True
        if self.remote:
            self.remote.cancel()  # the thread may be waiting for a training process still starting
        if not self.online.stop(timeout=60.0):
            self.node.get_logger().warning('adaptation thread did not stop within 60 s')
        if self.remote and not self.remote.close():
            self.node.get_logger().warning('adaptation: the training process did not stop in 10 s: killed')
        c = self.adapter.counters
        summary = (
            f'adaptation: {c.observed} keyframes, {c.updated} updates, {c.rolled_back} rolled back, '
            f'{c.skipped} skipped, {self.online.dropped} dropped, {self.online.failed} failed, '
            f'{c.behind} trained while behind'
        )
        if c.restarts or self.online.stale:
            summary += f', {c.restarts} restarts ({self.online.stale} keyframes before one not trained on)'
        self.node.get_logger().info(summary)
        if self.checkpoint and not self.online.learnt:
            # Nothing learnt in this run (or since a restart): writing the weights as loaded
            # would replace an earlier run's adapted checkpoint with them.
            self.node.get_logger().info(
                f'no adaptation update was accepted: {self.checkpoint} left as it was'
            )
        elif self.checkpoint:
            try:
                path = self.save()
                self.node.get_logger().info(f'adapted weights (version {self.slot.version}) saved to {path}')
            except (OSError, ValueError) as exc:
                self.node.get_logger().error(f'could not save the adapted weights: {exc}')
