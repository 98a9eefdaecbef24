"""``multi_view_node``: image + camera_info + PoseStamped -> semi-dense keyframe depth and score.

Poses come from any SLAM at their own rate and stamps, so the node keeps them in a bounded
:class:`~depth_fusion_ros.pose_buffer.PoseBuffer` and interpolates the pose at each image
stamp (linear translation, slerp). An image newer than the latest pose waits (bounded, see
``pose_wait``) because a SLAM usually publishes a frame's pose after the frame; an image the
buffer cannot cover (before the first pose, across a gap longer than ``max_pose_gap``, or
never reached by the poses in time) is dropped and counted.

Every posed frame is kept, undistorted on the working grid, in a bounded buffer of recent
frames: the only frames the multi-view search may use as neighbours (online mode: past
frames the node really received). The keyframe decision is deterministic given the input
stream (every ``keyframe_every``-th posed frame, or by motion), so a replay of the same bag
gives the same keyframes as the offline evaluation with the same stride.

A keyframe is announced on ``depth_fusion/keyframe/image`` (rgb8, undistorted, working grid)
and ``depth_fusion/keyframe/camera_info`` with the source header when the worker takes it,
before the multi-view estimate (``multi_view.method``: the temporal filter by default, or the
paper's sweep): the single-view node then runs the network in parallel. A keyframe
dropped from the work queue (latest-wins) is never announced, so every announced keyframe
gets a multi-view depth (possibly without estimates) and the fusion node never waits for
one that will not come.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import CameraInfo, Image

from ..camera import PinholeCamera
from ..data import messages
from ..data.sequence import Frame
from ..geometry import invert_pose, load_rotations, rotation_angle, transform_from_parameter
from ..multiview import native_cost, native_filter, native_scores
from ..multiview.focal_check import FocalEstimate
from ..multiview.mount_check import MountEstimate
from ..multiview.neighbours import NeighbourConfig, select_neighbours
from ..multiview.semidense import MultiViewConfig, estimate_semidense
from ..pose_buffer import PoseBuffer
from ..pose_corrections import new_world_from
from ..pose_jumps import PoseJump
from . import robot_inputs
from .announce import announce
from .base import PUBLISHER_CHECK_PERIOD, DepthFusionNode
from .check_process import CheckProcess
from .console import run_node
from .corrected_path import TOPIC_CORRECTED_PATH, correction_limits, read_path
from .diagnostics import Requirement
from .focal_check_runner import FocalCheckRunner
from .graph_events import EVENT_CHOSEN, EVENT_IMAGE, EVENT_IMAGE_DONE, EVENT_IMAGE_WAITING, GraphEvents
from .image_input import (
    CameraInput,
    InputError,
    WorkingImage,
    header_stamp_ns,
    pose_from_message,
)
from .info_wait import AwaitingCalibration
from .lens_topic import TOPIC_LENS_CAMERA_INFO, lens_qos
from .mount_check_runner import MountCheckRunner
from .multi_view_checks import CheckCorrections
from .multi_view_filter import FilterFeed
from .multi_view_params import (
    PARAMETERS,
    TOPIC_BIAS_STD,
    TOPIC_CAMERA_INFO,
    TOPIC_DEPTH,
    TOPIC_DEPTH_STD,
    TOPIC_IMAGE,
    TOPIC_KEYFRAME_CAMERA_INFO,
    TOPIC_KEYFRAME_IMAGE,
    TOPIC_KEYFRAME_POSE,
    TOPIC_METHOD,
    TOPIC_POSE,
    TOPIC_SCORE,
)
from .params import build_dataclass
from .pose_jump_params import pose_jump_limits
from .posing import PosingPublisher
from .qos import latched_qos, offers_latched, qos_profile
from .reliability import ignore_incompatible
from .time_offset_check_runner import TimeOffsetCheckRunner

NODE_NAME = 'multi_view_node'
#: A gap of this many of the stream's periods or more means images went missing (image_gap).
GAP_PERIODS = 1.8


@dataclass
class _Pending:
    image: WorkingImage
    received_at: float


@dataclass
class _KeyframeJob:
    key: Frame
    neighbours: list[Frame]
    camera: PinholeCamera
    header: Any
    received_at: float


def _image_name(stamp_ns: int, offset: float) -> str:
    """``image <stamp>`` for drop messages, with the pose-clock time it was looked up at when
    ``pose_time_offset`` is set (the pose span they quote is on that clock)."""
    stamp = messages.ns_to_sec(stamp_ns)
    return f'image {stamp:.3f}' if offset == 0.0 else f'image {stamp:.3f} (pose time {stamp + offset:.3f})'


class MultiViewNode(CheckCorrections, DepthFusionNode):
    """Poses images by stamp, decides keyframes and runs the semi-dense search on a worker."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, PARAMETERS, **kwargs)
        p = self.params
        self.config: MultiViewConfig = build_dataclass(MultiViewConfig, p, 'multi_view')
        self.neighbour_config: NeighbourConfig = build_dataclass(NeighbourConfig, p, 'neighbours')
        try:
            self.config.validate()
            self.neighbour_config.validate()
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        self.camera_input = CameraInput.from_parameters(p)
        try:
            self.T_pose_cam = transform_from_parameter(p['camera_from_pose_frame'])
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        #: ``pose_inverted``: each told pose is T_cw and read inverted (robot_inputs.py)
        self.pose_inverted = bool(p['pose_inverted'])
        self.device = str(p['device'])
        try:
            self.filter_feed = FilterFeed.from_parameters(
                p,
                self.config,
                self.device,
                lambda message: self.stats.dropped('filter_behind', message),
                lambda message: self.stats.dropped('filter_error', message),
                lambda message: self.stats.noted('filter_skipped', message),  # no output lost
                # A frame the filter takes is done once the filter is done with it: a paced
                # replay waits for that, so no frame queues in front of the next keyframe.
                lambda stamp_ns: self.events.event(stamp_ns, EVENT_IMAGE_DONE),
            )
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        try:
            self.focal_check = FocalCheckRunner.from_parameters(p, self._on_focal_estimate)
            if self.filter_feed is not None:
                prior = self.filter_feed.config.focal_uncertainty
                self.filter_feed.focal_uncertainty = lambda: self.focal_check.uncertainty(
                    prior, self.camera_input.lens_k1 != 0.0
                )
            self.time_offset_check = TimeOffsetCheckRunner.from_parameters(p, self._on_time_offset_estimate)
            self.mount_check = MountCheckRunner.from_parameters(p, self._on_mount_estimate)
        except ValueError as exc:
            raise ValueError(f'{self.get_name()}: {exc}') from None
        self.jump_limits = pose_jump_limits(p)
        self.correction_limits = correction_limits(p)
        self.pose_buffer = PoseBuffer(
            int(p['pose_buffer_size']), float(p['max_pose_gap']), jump_limits=self.jump_limits
        )
        self.frames: deque[Frame] = deque(maxlen=self.neighbour_config.window)
        self.pending: deque[_Pending] = deque()
        self.posed_count = 0
        self.keyframes_decided = 0
        #: The time offset check's correction the lookups use (``_pose_offset``)
        self._offset_correction = 0.0
        #: The mount check's turn of every camera pose once taken (``_take_mount_correction``), and
        #: the check result it last took
        self._mount_correction = np.eye(4)
        self._mount_taken: MountEstimate | None = None
        #: A mount verdict that came before the time offset check settled, said once it has
        #: (``_on_mount_estimate``), under its lock (the check's thread and the callbacks')
        self._mount_unsaid: MountEstimate | None = None
        self._mount_unsaid_lock = threading.Lock()
        #: The focal check result whose lens distortion was last taken (``_take_lens_correction``)
        self._lens_taken: FocalEstimate | None = None
        #: A whole frame's turn was taken and the mount check has not looked again since: a lens
        #: found meanwhile waits for it (``_take_lens_correction``)
        self._frame_tilt_unchecked = False
        #: The mount check found the told poses inverted (``_on_inverted_poses``): with
        #: ``mount_check.mode`` correct no multi-view depth is published from then on
        self._inverted_found: MountEstimate | None = None
        self._last_keyframe_pose: np.ndarray | None = None
        self._image_stamps = self.stamp_guard('image')
        self._pose_stamps = self.stamp_guard('pose')
        #: index of the first posed frame of the current stream (the every_k phase restarts there)
        self._stream_first_index = 0
        #: the first posed frame stamped at or after this begins a new stream (None: none due)
        self._restart_from_ns: int | None = None
        #: recent image periods (s), to tell a new stream's gap from the stream's own rhythm
        self._image_periods: deque[float] = deque(maxlen=10)
        self._newest_image_ns: int | None = None
        #: the newest image posed (camera clock), for where a corrected trajectory's world begins
        self._last_posed_ns: int | None = None
        self._last_input = time.monotonic()
        #: ``_last_input`` as a timer tick last found it quiet for ``pose_wait`` (``_give_up_pending``).
        self._quiet_mark: float | None = None
        #: frame_id of the pose stream (the world frame the keyframe poses are published in).
        self._world_frame = 'world'

        self._kf_image_pub = self.create_publisher(Image, TOPIC_KEYFRAME_IMAGE, self.output_qos)
        self._kf_info_pub = self.create_publisher(CameraInfo, TOPIC_KEYFRAME_CAMERA_INFO, self.output_qos)
        self._depth_pub = self.create_publisher(Image, TOPIC_DEPTH, self.output_qos)
        self._score_pub = self.create_publisher(Image, TOPIC_SCORE, self.output_qos)
        self._std_pub = self.create_publisher(Image, TOPIC_DEPTH_STD, self.output_qos)
        # the filter's focal length bias; the sweep has none, and sends nothing there
        with_bias = str(p['multi_view.method']) == 'filter'
        self._bias_pub = self.create_publisher(Image, TOPIC_BIAS_STD, self.output_qos) if with_bias else None
        self._kf_pose_pub = self.create_publisher(PoseStamped, TOPIC_KEYFRAME_POSE, self.output_qos)
        self._lens_pub = self.create_publisher(CameraInfo, TOPIC_LENS_CAMERA_INFO, lens_qos())
        self.posing = PosingPublisher(
            self, 'multi_view_node: pose_time_offset and the time offset check', int(p['pose_buffer_size'])
        )
        self._method_pub = announce(self, TOPIC_METHOD, str(p['multi_view.method']))
        self.events = GraphEvents(self)
        self.awaiting_info = AwaitingCalibration(float(p['camera_info_wait']), int(p['max_pending_images']))
        self.worker = self.make_worker('multi_view', self._process, on_lost=self._on_keyframe_lost)
        #: The calibration checks' runners (their diagnostics, and the wait for the keyframes).
        self.check_runners = (self.focal_check, self.time_offset_check, self.mount_check)
        self.check_process = self._check_process(p)
        for runner in self.check_runners:
            runner.busy = self._keyframe_path_busy
            runner.host = self.check_process
        image_qos = qos_profile(str(p['input_qos']), max(int(p['image_qos_depth']), int(p['qos_depth'])))
        self.subscribe_input(CameraInfo, TOPIC_CAMERA_INFO, self._on_camera_info, image_qos)
        self._latched_info: Any = None
        self._latched_info_timer = self.create_wall_timer(0.25, self._follow_latched_info)
        pose_qos = qos_profile(str(p['input_qos']), int(p['pose_qos_depth']))
        self.pose_input = robot_inputs.PoseSubscription(
            self, TOPIC_POSE, str(p['pose_type']), self._on_pose, pose_qos
        )
        self.image_topic = robot_inputs.subscribe_image(
            self, TOPIC_IMAGE, self._on_image, image_qos, str(p['image_transport'])
        )
        self.subscribe(PathMsg, TOPIC_CORRECTED_PATH, self._on_corrected_path, self.input_qos)
        self.transport_check = robot_inputs.TransportCheck(self, TOPIC_IMAGE, str(p['image_transport']))
        self.create_wall_timer(PUBLISHER_CHECK_PERIOD, self.transport_check.check)
        self.create_wall_timer(0.25, self._give_up_pending)
        self.get_logger().info(
            f'multi-view on {self.device}, keyframes {p["keyframe_policy"]}'
            + (f' every {p["keyframe_every"]}' if p['keyframe_policy'] == 'every_k' else '')
            + f', {p["num_neighbours"]} neighbours among the last {self.neighbour_config.window} frames; '
            f'{self.resolve_topic_name(self.image_topic)} + {self.resolve_topic_name(TOPIC_POSE)} -> '
            f'{self.resolve_topic_name(TOPIC_DEPTH)}'
        )
        # Every published pose and every image between two poses goes through them.
        load_rotations()
        if self.device == 'cpu':
            native_cost.prepare()  # the matching cost and search: built here, not at the first frame
            native_scores.prepare()  # the sweep's coarse scores
            native_filter.prepare()  # the filter's descriptors, choice of rows, seed bracket and update
        self.events.ready()

    # --- callbacks (light: decode, check, buffer) ---------------------------------------------------

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.stats.received('camera_info')
        try:
            self.camera_input.update(msg)
        except InputError as exc:
            self.stats.dropped(exc.reason, str(exc))
            return
        for _, image_msg in self.awaiting_info.release():
            self._on_image(image_msg, counted=True)

    def _follow_latched_info(self) -> None:
        """Also subscribe transient local once a latched camera_info publisher shows up.

        A client that publishes its calibration once, latched, sent it before this node
        existed: only a transient-local subscription gets that sample. Such a subscription does
        not match the usual volatile publisher, whose process would then warn about an
        incompatible QoS at every start, so it is made only for a latched publisher (its
        sample then arrives twice, which changes nothing).
        """
        if self.camera_input.calibration is not None:  # a calibration came: nothing to wait for
            self._latched_info_timer.cancel()
            return
        topic = self.resolve_topic_name(TOPIC_CAMERA_INFO)
        infos = self.get_publishers_info_by_topic(topic)
        if not any(offers_latched(i) for i in infos):
            return
        self._latched_info_timer.cancel()
        self._latched_info = self.subscribe(
            CameraInfo, TOPIC_CAMERA_INFO, self._on_camera_info, latched_qos(), ignore_incompatible()
        )

    def _on_pose(self, msg: Any) -> None:
        self.stats.received('pose')
        self._last_input = time.monotonic()
        try:
            T_told = pose_from_message(msg)
            T_wc = (invert_pose(T_told) if self.pose_inverted else T_told) @ self.T_pose_cam
            stamp_ns = header_stamp_ns(msg)
            if self._pose_stamps.check(stamp_ns):
                self._start_over('pose', stamp_ns)
        except InputError as exc:
            self.stats.dropped(exc.reason, str(exc))
            return
        try:
            jump = self.pose_buffer.insert(messages.ns_to_sec(stamp_ns), T_wc)
        except ValueError as exc:  # PoseError: not a rigid transform
            self.stats.dropped('bad_pose', f'pose: {exc}')
            return
        if jump is not None:
            self._on_pose_jump(jump)
        self._world_frame = msg.header.frame_id or self._world_frame
        self._resolve_pending()

    def _on_corrected_path(self, msg: Any) -> None:
        """A loop closure's corrected trajectory: the buffered poses move with it, so the images
        still to be posed get corrected poses. When the newest pose it covers moved by
        ``correction_min_*`` or more, the frames already posed are in the uncorrected world: the
        frame history and the filter start over at the next posed frame (``pose_correction``),
        as at a pose jump, so no neighbour and no propagated estimate crosses the correction,
        however small it is against the jump limits."""
        world = self._world_frame if len(self.pose_buffer) else ''  # (its default until a pose came)
        path = read_path(self.stats, msg, self.T_pose_cam, world, self.pose_inverted)
        if path is None:
            return
        stamps, poses = path
        move = self.pose_buffer.correct(stamps, poses, self.correction_limits.max_gap)
        if move is not None and self.correction_limits.counts(*move):
            self._restart_from_ns = self._corrected_world_from(msg, float(np.max(stamps)))
            self.stats.noted(
                'pose_correction',
                f'a corrected trajectory moved the newest pose it covers by {move[0]:.3f} m and '
                f'{move[1]:.2f} deg: poses corrected, frame history and filter start over',
            )
        self._resolve_pending()

    def _corrected_world_from(self, msg: Any, path_end: float) -> int:
        """The camera stamp (ns) from which posed images are in the corrected world
        (:func:`new_world_from`; 0: the next posed image)."""
        offset = self._pose_offset()
        newest = None if self._last_posed_ns is None else messages.ns_to_sec(self._last_posed_ns) + offset
        start = new_world_from(messages.ns_to_sec(messages.stamp_to_ns(msg.header.stamp)), path_end, newest)
        return 0 if start is None else messages.sec_to_ns(start - offset)

    def _on_image(self, msg: Any, counted: bool = False) -> None:
        received_at = self._last_input = time.monotonic()
        if not counted:
            self.stats.received('image')
        self._take_lens_correction(header_stamp_ns(msg), msg.header.frame_id)
        try:
            image = self.camera_input.working_image(msg)
            previous_ns = self._image_stamps.last_ns
            if self._image_stamps.check(image.stamp_ns):
                self._start_over('image', image.stamp_ns)
            elif previous_ns is not None:
                self._check_gap(previous_ns, image.stamp_ns)
        except InputError as exc:
            if exc.reason == 'no_camera_info':
                for stamp_ns, _ in self.awaiting_info.hold(header_stamp_ns(msg), msg):
                    self.stats.dropped(exc.reason, str(exc))
                    self._handled(stamp_ns)
                return
            self.stats.dropped(exc.reason, str(exc))
            self._handled(header_stamp_ns(msg))
            return
        self._newest_image_ns = image.stamp_ns
        self.pending.append(_Pending(image, received_at))
        limit = int(self.params['max_pending_images'])
        hint = self._pose_lag_hint() if len(self.pending) > limit else ''
        while len(self.pending) > limit:
            old = self.pending.popleft()
            self.stats.dropped(
                'pose_wait_overflow',
                f'image {messages.ns_to_sec(old.image.stamp_ns):.3f} dropped: more than '
                f'{limit} images waiting for poses{hint}',
            )
            self._handled(old.image.stamp_ns)
        self._resolve_pending()
        if self.pending and self.pending[-1].image is image:  # still waiting for its pose
            self.events.event(image.stamp_ns, EVENT_IMAGE_WAITING)

    def _handled(self, stamp_ns: int) -> None:
        """The graph's events of an image this node is done with (dropped, or posed and not for
        the filter): ``image`` (handled: counted, and a keyframe decision made) and ``image_done``
        (nothing of it left to do here), which a paced replay waits for."""
        self.events.event(stamp_ns, EVENT_IMAGE)
        self.events.event(stamp_ns, EVENT_IMAGE_DONE)

    def _start_over(self, stream: str, stamp_ns: int) -> None:
        """A new stream began (``stream`` jumped back): forget what the previous one left.

        Its poses would be interpolated into the new images, its frames chosen as neighbours and
        its filter estimates propagated into the new keyframes, all in another trajectory (a
        replayed sequence starts where the camera was then, another sequence in another world).
        Images of it still waiting for a pose are dropped (``stream_restart``); keyframes
        already chosen are finished. The other input's guard starts over too, so its first
        message of the new stream is taken as it comes.
        """
        (self._pose_stamps if stream == 'image' else self._image_stamps).reset()
        self.pose_buffer.clear()
        self.posing.forget_keyframes()
        while self.pending:
            old = self.pending.popleft()
            self.stats.dropped(
                'stream_restart', f'image {messages.ns_to_sec(old.image.stamp_ns):.3f}: its stream ended'
            )
            self._handled(old.image.stamp_ns)
        self._newest_image_ns = None
        self._last_posed_ns = None
        self._image_periods.clear()
        self._restart_from_ns = 0  # the next posed frame, whatever its stamp
        self.note_stream_restart(stream, stamp_ns, 'poses, frame history and filter start over')

    def _on_pose_jump(self, jump: PoseJump) -> None:
        """The pose source jumped (relocalised, closed a loop): frames from before the jump are
        in another world than those after it. Count it (note ``pose_jump``, a throttled
        warning) and start the frame history and the filter over at the first frame after it,
        so that no neighbour and no propagated estimate crosses it. The images between the two
        poses are dropped when their turn comes (``pose_jump``: nothing to interpolate)."""
        offset = self._pose_offset()
        after_ns = messages.sec_to_ns(jump.after - offset)  # on the camera's clock
        if self._restart_from_ns is None or after_ns > self._restart_from_ns:
            self._restart_from_ns = after_ns
        self.stats.noted(
            'pose_jump',
            f'the pose jumped {jump.describe(self.jump_limits)} at {jump.after:.3f} s: the pose source '
            'relocalised? frame history and filter start over (max_pose_speed, max_pose_angular_speed)',
        )

    def _check_gap(self, previous_ns: int, stamp_ns: int) -> None:
        """A gap in the images far longer than the stream's rhythm (at least
        ``stream_restart_jump`` s and 10 of its recent periods) begins a new stream too: another
        sequence played after this one, with later stamps. Its frames must not update this
        one's keyframe, nor be chosen as neighbours of it. The poses are kept (their own
        ``max_pose_gap`` keeps frames across the gap apart)."""
        period = messages.ns_to_sec(stamp_ns - previous_ns)
        limit = float(self.params['stream_restart_jump'])
        if len(self._image_periods) >= 3:
            usual = float(np.median(self._image_periods))
            if limit > 0 and period >= max(limit, 10.0 * usual):
                self._image_periods.clear()
                self._restart_from_ns = stamp_ns
                self.note_stream_restart(
                    'image',
                    stamp_ns,
                    f'after {period:.1f} s without images: frame history and filter start over',
                )
                return
            self._note_missing_images(period, usual, stamp_ns)
        self._image_periods.append(period)

    def _note_missing_images(self, period: float, usual: float, stamp_ns: int) -> None:
        """Images missing inside the stream (a gap of about two periods or more), counted as a
        note (``image_gap``, one per missing image): the camera or the transport lost them
        before this node's callback, and a busy node's subscription overflows its history
        (``image_qos_depth``). Not a drop (nothing of ours was lost), but never unsaid: a
        live 2-core run lost 6 of 37 images that way, with no count anywhere."""
        missing = round(period / usual) - 1  # (periods are > 0: the stamp guard refuses repeats)
        if period >= GAP_PERIODS * usual and missing >= 1:
            self.stats.noted(
                'image_gap',
                f'{missing} image(s) missing before {messages.ns_to_sec(stamp_ns):.3f} s '
                f'({period * 1e3:.0f} ms after the one before, period {usual * 1e3:.0f} ms): lost by the '
                'camera or the transport, '
                'or by this node when busy (image_qos_depth)',
                count=missing,
            )

    def _restart_frames(self) -> None:
        """The frame history, the keyframe phase and the filter of a new stream (at its first
        posed frame: images of the previous one still waiting for their pose belong to it)."""
        self.frames.clear()
        self._last_keyframe_pose = None
        self._stream_first_index = self.posed_count
        if self.filter_feed is not None:
            self.filter_feed.restart(self.posed_count)
        self._restart_from_ns = None

    def _pose_lag_hint(self) -> str:
        """How far the pose stream is behind the images, and the usual cause when it stalls
        while images flow: one process publishing raw images larger than Fast DDS's default
        0.5 MB shared-memory segment (its other topics stall for the reliability repair)."""
        span = self.pose_buffer.span
        if span is None or self._newest_image_ns is None:
            return ''
        lag = messages.ns_to_sec(self._newest_image_ns) + self._pose_offset() - span[1]
        return (
            f'; the latest pose is {lag:.1f} s behind the newest image (raw images over 0.5 MB sent '
            'through shared memory by a publisher with Fast DDS defaults stall the other topics of '
            'its process; the package profile reads the image topic over UDP to prevent it: is '
            'another profile set? docs/nodes.md "Large raw images")'
        )

    def _resolve_pending(self) -> None:
        """Pose every waiting image the buffer now covers, in stamp order; drop the hopeless ones."""
        wait_ns = messages.sec_to_ns(float(self.params['pose_wait']))
        self._take_offset_correction()
        self._take_mount_correction()
        offset = self._pose_offset()
        while self.pending:
            head = self.pending[0]
            stamp = messages.ns_to_sec(head.image.stamp_ns) + offset  # on the pose source's clock
            what = _image_name(head.image.stamp_ns, offset)
            span = self.pose_buffer.span
            if span is None or stamp > span[1]:
                # The pose of this image may still come; give up once the stream is pose_wait ahead.
                if (
                    self._newest_image_ns is not None
                    and self._newest_image_ns - head.image.stamp_ns > wait_ns
                ):
                    self.pending.popleft()
                    newest = 'no pose yet' if span is None else f'latest pose {span[1]:.3f}'
                    self.stats.dropped('no_pose', f'{what} has no pose ({newest}); dropped')
                    self._handled(head.image.stamp_ns)
                    continue
                return
            self.pending.popleft()
            if stamp < span[0]:
                self.stats.dropped('no_pose', f'{what} is older than the first pose {span[0]:.3f}')
            else:
                lookup = self.pose_buffer.lookup(stamp)
                if lookup.pose is None:
                    self.stats.dropped(lookup.key, f'{what}: {lookup.reason}')
                else:
                    self._on_posed_frame(head, lookup.pose)  # sends the frame's events
                    continue
            self._handled(head.image.stamp_ns)

    def _give_up_pending(self, reason: str = '') -> None:
        """Drop (``no_pose``) the images still waiting once no image nor pose came for ``pose_wait``
        seconds: at the end of a stream nothing will move the stamp-time wait on, and images of
        a bag without poses must be counted, not kept silently."""
        if not self.pending:
            return
        quiet = time.monotonic() - self._last_input
        if not reason and quiet <= float(self.params['pose_wait']):
            return
        if not reason and self._quiet_mark != self._last_input:
            # Quiet on this tick. A starved executor (a loaded machine) serves a ready timer
            # before the messages already waiting for it, so a pose may be queued behind this
            # very call: decide on a later tick, once a whole executor round brought no input.
            self._quiet_mark = self._last_input
            return
        span = self.pose_buffer.span
        why = reason or f'no input for {quiet:.1f} s'
        latest = (
            f'latest pose {span[1]:.3f}'
            if span
            else f'no pose ever received on {self.pose_input.resolved_topic}'
        )
        count = len(self.pending)
        stamps = [p.image.stamp_ns for p in self.pending]
        self.pending.clear()
        self.stats.dropped('no_pose', f'{count} image(s) never got a pose ({latest}; {why})', count=count)
        for stamp_ns in stamps:  # handled (dropped): a run counts them, a paced replay moves on
            self._handled(stamp_ns)

    def held_items(self) -> int:
        return len(self.pending)

    def diagnostic_requirements(self) -> list[Requirement]:
        reqs = [Requirement('pose', 'image', self.pose_input.resolved_topic)]
        if self.camera_input.fixed_intrinsics is None:
            reqs.append(Requirement('camera_info', 'image', self.resolve_topic_name(TOPIC_CAMERA_INFO)))
        return reqs

    def readiness(self) -> tuple[bool, str]:
        waiting = []
        if self.camera_input.fixed_intrinsics is None and self.camera_input.calibration is None:
            waiting.append('camera_info')
        if self.pose_buffer.span is None:
            waiting.append(f'a pose on {self.pose_input.resolved_topic} ({self.pose_input.description})')
        return not waiting, ', '.join(waiting)

    def diagnostic_extra(self) -> dict[str, Any]:
        extra = {
            'image topic': self.resolve_topic_name(self.image_topic),
            'pose topic': self.pose_input.resolved_topic,
            'pose type': self.pose_input.description,
            'posed frames': self.posed_count,
            'keyframes': self.keyframes_decided,
        }
        if self.filter_feed is not None:
            extra['filter frames passed over (filter.max_update_rate)'] = self.filter_feed.rate_skipped
            extra['filter keyframes across a jump (estimates confirmed again)'] = self.filter_feed.jumps
            extra['filter frames with a refined pose (filter.refine_poses)'] = self.filter_feed.refined_poses
            extra['filter frames that kept their told pose (refinement failed)'] = (
                self.filter_feed.kept_told_poses
            )
        extra['focal length check'] = self.focal_check.status()
        extra['lens k1 added to the calibration (focal length check)'] = round(self.camera_input.lens_k1, 4)
        extra['time offset check'] = self.time_offset_check.status()
        extra['mount check'] = self.mount_check.status()
        # Why a check can take longer than its pairs: it waits for the keyframes (check_runner.py).
        waited, cpu = self._check_totals()
        extra['calibration checks: seconds waited for the keyframes'] = round(waited, 2)
        extra['calibration checks: CPU seconds'] = round(cpu, 2)
        return extra

    def _check_process(self, p: dict[str, Any]) -> CheckProcess | None:
        """The checks' own process, started now, or ``None``:
        asked not to (``calibration_checks.process``), or every check is off."""
        if not bool(p['calibration_checks.process']):
            return None
        if all(r.config.mode == 'off' for r in self.check_runners):
            return None

        def lost(why: str) -> None:
            self.get_logger().error(
                f"the calibration checks' process is gone: {why}; the checks go on on this node's "
                'threads, each from its next frame'
            )

        process = CheckProcess(int(p['calibration_checks.nice']), on_lost=lost)
        process.start()  # it imports the checks' code before the stream comes
        return process

    def _check_totals(self) -> tuple[float, float]:
        """Seconds the three checks waited for the keyframe path, and CPU seconds they took."""
        return sum(r.waited for r in self.check_runners), sum(r.cpu for r in self.check_runners)

    def destroy_node(self) -> None:
        if not self._destroyed:
            self._give_up_pending('node shutting down')
        super().destroy_node()

    def close_threads(self) -> None:
        """The checks and the filter feed publish (estimates, ``image_done``): they stop before
        the publishers go, once the worker is done with the keyframe in hand."""
        for runner in self.check_runners:
            runner.close()
        if self.check_process is not None:
            self.check_process.close()
        waited, cpu = self._check_totals()
        if cpu > 0.0:  # what the checks took from the keyframes, said once
            self.get_logger().info(
                f'calibration checks: {cpu:.1f} CPU s over the run, {waited:.1f} s waited for the keyframes'
            )
        if self.filter_feed is not None:
            self.filter_feed.close()

    def _on_posed_frame(self, pending: _Pending, T_wc: np.ndarray) -> None:
        """Take one posed frame: the checks, the keyframe policy, the filter, and the frame's
        events (``chosen``, ``image``, ``image_done``: see :meth:`_handled`)."""
        image = pending.image
        restarted = self._restart_from_ns is not None and image.stamp_ns >= self._restart_from_ns
        if restarted:
            self._restart_frames()
        if restarted or not self.posing.published:  # a posing correction restarts the history
            self._publish_posing(image.stamp_ns, image.header.frame_id)
        T_wc = T_wc @ self._mount_correction
        frame = Frame(self.posed_count, messages.ns_to_sec(image.stamp_ns), image.rgb, T_wc)
        self.posed_count += 1
        self._last_posed_ns = image.stamp_ns
        self.focal_check.offer(frame, image.camera)
        self.time_offset_check.offer(frame, image.camera)
        # From the start: a time offset correction starts it over (its pairs were posed at the
        # old offset), and its verdict waits for the time offset check (_take_mount_correction).
        self.mount_check.offer(frame, image.camera)
        camera = self.focal_check.camera_for(image.camera, self.camera_input.lens_k1 != 0.0)
        job = None
        if self._is_keyframe_candidate(frame):
            neighbours = self._select_neighbours(frame, camera)
            if len(neighbours) >= int(self.params['min_neighbours']):
                job = _KeyframeJob(frame, neighbours, camera, image.header, pending.received_at)
        if job is not None:
            self.keyframes_decided += 1
            self.posing.keyframe(image.stamp_ns)
            self._last_keyframe_pose = T_wc
            self.events.event(image.stamp_ns, EVENT_CHOSEN)
        # The filter sees every posed frame, as it comes; none once the poses were found inverted
        # (their multi-view depth is withheld: _withheld_for_inverted_poses).
        if self.filter_feed is not None and self._inverted_found is None:
            # After 'chosen' (same writer): a replayer seeing this ack knows the decision.
            self.events.event(image.stamp_ns, EVENT_IMAGE)
            # 'image_done' comes from the feed, once the filter is done with the frame.
            self.filter_feed.append(frame, camera, keyframe=job is not None, token=image.stamp_ns)
        else:
            self._handled(image.stamp_ns)
        if job is not None:
            self.worker.submit(job)
        self.frames.append(frame)

    # --- keyframe policy ----------------------------------------------------------------------------

    def _is_keyframe_candidate(self, frame: Frame) -> bool:
        if self.params['keyframe_policy'] == 'every_k':
            return (frame.index - self._stream_first_index) % int(self.params['keyframe_every']) == 0
        if self._last_keyframe_pose is None:
            return True
        delta = invert_pose(self._last_keyframe_pose) @ frame.pose
        moved = float(np.linalg.norm(delta[:3, 3])) >= float(self.params['keyframe_min_translation'])
        turned = np.degrees(rotation_angle(delta[:3, :3])) >= float(self.params['keyframe_min_rotation_deg'])
        return moved or turned

    def _select_neighbours(self, key: Frame, camera: PinholeCamera) -> list[Frame]:
        """Up to ``num_neighbours`` of the buffered past frames, chosen by the core's online rule."""
        history = list(self.frames)
        if not history:
            return []
        poses = np.stack([f.pose for f in history] + [key.pose])
        chosen = select_neighbours(
            poses,
            len(history),
            int(self.params['num_neighbours']),
            mode='online',
            camera=camera,
            config=self.neighbour_config,
            warn=lambda message: self.stats.noted('zero_baseline', f'keyframe {key.stamp:.3f}: {message}'),
        )
        return [history[i] for i in chosen]

    def _keyframe_path_busy(self) -> bool:
        """A keyframe or a filter frame in hand or waiting: the calibration checks wait before
        their next sample (nodes/check_runner.py), so the first keyframes of a stream do not
        share the CPU with them."""
        feed = self.filter_feed
        return not self.worker.idle() or (feed is not None and not feed.idle())

    def _on_keyframe_lost(self, job: _KeyframeJob, reason: str) -> None:
        """A chosen keyframe the worker dropped before announcing it: the graph must hear of it."""
        if self.filter_feed is not None:
            self.filter_feed.discard(job.key.index)
        self.events.dropped(header_stamp_ns(job), reason)

    # --- worker (heavy) -----------------------------------------------------------------------------

    def _estimate(self, job: _KeyframeJob) -> Any:
        """The keyframe's multi-view result: the filter's (fed every posed frame) or the sweep's."""
        if self.filter_feed is not None:
            return self.filter_feed.result_for(job.key, job.camera)
        return estimate_semidense(
            job.key.gray,
            job.key.pose,
            [f.gray for f in job.neighbours],
            [f.pose for f in job.neighbours],
            job.camera,
            self.config,
            device=self.device,
            neighbours=[f.index for f in job.neighbours],
        )

    def _note_withheld(self, result: Any) -> None:
        """Say why a filter keyframe has no multi-view depth when the minority rule withheld it."""
        share = getattr(result, 'withheld_fraction', None)
        if share is not None:
            self.stats.noted(
                'filter_minority',
                f'only {share:.0%} of the measured estimates passed the precision test '
                f'(< filter.min_published_fraction): no multi-view depth for this keyframe',
            )

    def _process(self, job: _KeyframeJob) -> None:
        kind = messages.RCLPY
        self._kf_info_pub.publish(messages.camera_info_msg(job.camera, job.header, kind=kind))
        self._kf_image_pub.publish(messages.rgb_image_msg(job.key.rgb, job.header, kind=kind))
        pose_header = messages.header_msg(job.header.stamp, self._world_frame, kind=kind)
        self._kf_pose_pub.publish(messages.pose_stamped_msg(job.key.pose, pose_header, kind=kind))
        self.stats.published('keyframe')
        nothing = np.full((job.camera.height, job.camera.width), np.nan, dtype=np.float32)
        depth = score = std = bias = nothing  # announced: downstream must still hear of the keyframe
        try:
            if not self._withheld_for_inverted_poses(job):
                result = self._estimate(job)
                self._note_withheld(result)
                depth, score = result.depth, result.score.astype(np.float32)
                std = np.asarray(result.depth_std, dtype=np.float32)
                shared = getattr(result, 'bias_std', None)
                bias = nothing if shared is None else np.asarray(shared, dtype=np.float32)
        except Exception as exc:
            self.stats.dropped('processing_error', f'multi-view search failed: {type(exc).__name__}: {exc}')
            self.get_logger().debug(traceback.format_exc())
            depth = score = std = bias = nothing
        # before the depth, so the fusion node has them when the depth completes the keyframe
        self._std_pub.publish(messages.image_msg(std, '32FC1', job.header, kind=kind))
        if self._bias_pub is not None:
            self._bias_pub.publish(messages.image_msg(bias, '32FC1', job.header, kind=kind))
        self._depth_pub.publish(messages.depth_image_msg(depth, job.header, kind=kind))
        self._score_pub.publish(messages.image_msg(score, '32FC1', job.header, kind=kind))
        self.stats.published('depth')
        self.stats.processed(time.monotonic() - job.received_at)


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point: ``multi_view_node --ros-args --params-file config/depth_fusion.yaml``."""
    return run_node(MultiViewNode, args, udp_image_topics=(TOPIC_IMAGE,), node_name=NODE_NAME)


if __name__ == '__main__':
    raise SystemExit(main())
