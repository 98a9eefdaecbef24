"""What ``multi_view_node`` does with its calibration checks' verdicts (focal length, time
offset, mount) and how it says the posing they lead to.

Why apart from the node: the node poses images, decides keyframes and runs the search; taking
a correction is a separate decision with its own state (the offset and the turn taken, the
restart of the frame history) and its own messages. :class:`CheckCorrections` is a mixin of
:class:`~depth_fusion_ros.nodes.multi_view_node.MultiViewNode`: it reads the node's check
runners, pose buffer, posing publisher and counters, which the node builds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..camera import PinholeCamera
from ..data.messages import ns_to_sec
from ..geometry import matrix_to_quat
from ..multiview.focal_check import FocalEstimate
from ..multiview.mount_check import MountEstimate
from ..multiview.time_offset_check import TimeOffsetEstimate
from ..pose_buffer import PoseBuffer
from ..pose_corrections import Posing
from .focal_check_runner import FocalCheckRunner
from .image_input import header_stamp_ns
from .lens_topic import lens_info_msg
from .mount_check_runner import MountCheckRunner
from .posing import TOPIC_REPOSED_KEYFRAMES, PosingPublisher
from .time_offset_check_runner import TimeOffsetCheckRunner


class CheckCorrections:
    """The checks' verdicts said once, and their corrections taken (see module)."""

    # Built by the node's constructor.
    params: Any
    stats: Any
    T_pose_cam: np.ndarray
    pose_buffer: PoseBuffer
    posing: PosingPublisher
    focal_check: FocalCheckRunner
    time_offset_check: TimeOffsetCheckRunner
    mount_check: MountCheckRunner
    _offset_correction: float
    _mount_correction: np.ndarray
    _mount_taken: MountEstimate | None
    _mount_unsaid: MountEstimate | None
    _mount_unsaid_lock: Any  # threading.Lock
    _restart_from_ns: int | None
    _lens_taken: FocalEstimate | None
    _inverted_found: MountEstimate | None
    pose_inverted: bool
    filter_feed: Any  # nodes/multi_view_filter.py FilterFeed, or None (the sweep)
    camera_input: Any  # nodes/image_input.py CameraInput
    _world_frame: str
    get_logger: Callable[[], Any]  # rclpy.node.Node's

    def _publish_posing(self, stamp_ns: int, camera_frame: str) -> None:
        """Say the posing from the frame stamped ``stamp_ns`` on (nodes/posing.py). After a time
        offset correction the keyframes posed before it are read again at the corrected offset
        from the pose buffer, so the map moves them where they were (their depth stays as the
        old poses made it)."""
        posing = Posing(self.T_pose_cam @ self._mount_correction, self._pose_offset())

        def reread(stamps: list[float], before: float, after: float) -> list[np.ndarray | None]:
            poses = self.pose_buffer.reread(stamps, before, after)
            return [None if T is None else T @ self._mount_correction for T in poses]

        reposed = self.posing.publish(stamp_ns, camera_frame, posing, reread, self._world_frame)
        if reposed is not None:
            found, before = reposed
            others = '' if found == before else '; the others are older than the pose buffer or across a jump'
            self.get_logger().info(
                f'{found} of the {before} keyframes posed before the time offset correction re-read at it '
                f'({TOPIC_REPOSED_KEYFRAMES}: map_node moves them){others}'
            )

    # --- focal length check ------------------------------------------------------------------------

    def _on_focal_estimate(self, camera: PinholeCamera, estimate: FocalEstimate) -> None:
        """The focal check's result for ``camera`` (its thread), said once; ``_on_posed_frame``
        takes the corrected camera from the runner (``camera_for``), the image callback a lens
        distortion (``_take_lens_correction``, which says it)."""
        if estimate.lens_distorted:  # whatever the focal length: the images show a lens
            if not self._lens_correctable():
                self.stats.noted('lens_distortion', f'{estimate.message()} ({camera.width}x{camera.height})')
            return
        if estimate.verdict == 'suspect':  # warned once, not taken: the fit is not sure enough
            self.stats.noted('focal_suspect', f'{estimate.message()} ({camera.width}x{camera.height})')
            return
        if estimate.poses_unfit:  # a warning, once: the poses are not this camera's, or too noisy
            self.stats.noted('focal_poses_unfit', f'{estimate.message()} ({camera.width}x{camera.height})')
            return
        if estimate.verdict != 'disagrees':
            self.get_logger().info(f'{estimate.message()} ({camera.width}x{camera.height})')
            return
        if self.camera_input.lens_k1 != 0.0:
            then = (
                '; not taken: the images are undistorted with a lens the check fitted, and what the fit '
                'leaves of the lens reads as a focal error too'
            )
        elif self.focal_check.config.mode == 'correct':
            then = (
                '; focal_check.mode correct: the multi-view depth and the keyframe camera_info use '
                f'fx {estimate.fx:.1f}, fy {estimate.fy:.1f} px from now on'
            )
        else:
            then = ' (focal_check.mode correct would use it)'
        self.stats.noted('focal_disagrees', estimate.message() + then)  # logged as a warning, once

    def _lens_correctable(self) -> bool:
        """Whether a lens distortion the focal check finds is taken: ``focal_check.mode`` correct
        and a calibration a radial term can be added to (not a fisheye model)."""
        return self.focal_check.config.mode == 'correct' and self.camera_input.can_correct_lens()

    def _take_lens_correction(self, stamp_ns: int, frame_id: str = '') -> None:
        """Take a lens distortion the focal check found (callback thread, before the image
        stamped ``stamp_ns`` is undistorted): its ``k1`` is added to the calibration from this
        image on (``data/lens_correction.py``), and the frame history, the filter, the focal
        length check and the mount check start over at it. Their frames were seen through the
        lens; the focal length is then checked again on the undistorted images. A second fit
        on those adds to the first. The calibration taken is published for the nodes that read
        the raw camera themselves (``lens_topic.py``)."""
        result = self.focal_check.result
        if result is None or result is self._lens_taken or not result.lens_distorted:
            return
        if self._frame_tilt_unchecked and self.mount_check.config.mode != 'off':
            # After a frame turn both checks start over; a mount tilt still left fakes a lens
            # (the `mount_tilt` robot of seed 201 told its body frame: a 2 deg tilt read as
            # k1 -0.163). It is taken once the mount check has looked again and not turned the
            # camera (a turn starts the focal check over, and the lens goes with it).
            return
        self._lens_taken = result
        if not self._lens_correctable():
            return  # said by _on_focal_estimate
        self.camera_input.lens_k1 += result.lens.k1
        taken = self.camera_input.calibration_in_use()
        if taken is not None:
            self._lens_pub.publish(lens_info_msg(taken, stamp_ns, frame_id))
        if self._restart_from_ns is None or stamp_ns > self._restart_from_ns:
            self._restart_from_ns = stamp_ns
        self.focal_check.restart()
        self.mount_check.restart()
        with self._mount_unsaid_lock:  # its pairs were seen through the lens
            self._mount_unsaid = None
        k1 = self.camera_input.lens_k1
        own = self.camera_input.told_distorted()
        fix = f'{k1:+.3f} added to D[0]' if own else f'D [{k1:.3f}, 0, 0, 0, 0]'
        self.stats.noted(
            'lens_corrected',
            f'{result.message()}; focal_check.mode correct: k1 {k1:+.3f} added to the calibration the '
            f'images are undistorted with, from the image stamped {ns_to_sec(stamp_ns):.3f} s on '
            f'(camera_info {fix} would do it from the start), frame history, filter, focal length and '
            'mount checks start over',
        )

    # --- time offset check ---------------------------------------------------------------------------

    def _pose_offset(self) -> float:
        """Seconds from an image's stamp to the pose time it is posed at: ``pose_time_offset``
        plus the time offset check's correction once taken (:meth:`_take_offset_correction`)."""
        return float(self.params['pose_time_offset']) + self._offset_correction

    def _take_offset_correction(self) -> None:
        """Take the time offset check's correction once it has one (``time_offset_check.mode``
        correct; callback thread, before images are posed). It starts the frame history, the
        filter and the focal length check over at the next posed frame: the frames posed before
        it were posed at the other offset, so no neighbour, propagated estimate or image pair
        mixes the two."""
        correction = self.time_offset_check.correction
        if correction == self._offset_correction:
            return
        self._offset_correction = correction
        self._restart_from_ns = 0  # the next posed frame, whatever its stamp
        self.focal_check.restart()  # its pairs were posed at the old offset
        self.mount_check.restart()
        with self._mount_unsaid_lock:  # a verdict on those pairs is not said either
            self._mount_unsaid = None
        self.stats.noted(
            'time_offset_disagrees',
            f'{self.time_offset_check.result.message()}; time_offset_check.mode correct: poses are '
            f'read at image stamp {self._pose_offset():+.3f} s from now on, frame history and filter '
            'start over',
        )

    def _on_time_offset_estimate(self, camera: PinholeCamera, estimate: TimeOffsetEstimate) -> None:
        """The time offset check's result (its thread), said once; in correct mode the callbacks
        take the correction (``_take_offset_correction``) and say it then."""
        self._say_verdict('time_offset', estimate, self.time_offset_check.config.mode)

    def _say_verdict(self, check: str, estimate: Any, mode: str, hint: str = '') -> None:
        """A check's verdict said once: ``suspect`` as a note (warned once, never taken), a
        disagreement the node does not take (``mode`` warn) as a note naming the mode that
        would, agreement and ``unobservable`` as an info line. A disagreement taken is said by
        the callbacks when they take it. ``hint``: what the user's configuration could hold."""
        if estimate.verdict == 'suspect':
            self.stats.noted(f'{check}_suspect', estimate.message())
        elif estimate.verdict != 'disagrees':
            self.get_logger().info(estimate.message())
        elif mode != 'correct':
            then = f'; {hint}' if hint else ''
            self.stats.noted(
                f'{check}_disagrees', f'{estimate.message()} ({check}_check.mode correct would use it){then}'
            )

    # --- mount check -------------------------------------------------------------------------------

    def _take_mount_correction(self) -> None:
        """Take the mount check's turn once it has one (``mount_check.mode`` correct; callback
        thread, before images are posed; a check of a camera seen anew adds its own). As a time
        offset correction, it starts the frame history, the filter and the focal length check
        over at the next posed frame.

        Only once the time offset check has settled: an offset fakes a turn. The mount check
        collects its pairs from the start meanwhile (until 2026-11-30 it began only then, and a
        short stream ended before its pairs were in); an offset correction starts it over
        (``_take_offset_correction``), and a verdict that came before is said now.

        A whole frame's turn (``MountEstimate.frame``: the told poses are another frame's) does
        not wait: no time offset fakes a turn by whole axes, and the time offset check's own
        pairs were posed in the wrong frame, so it starts over. Waiting, the ``handheld`` robot
        told its body frame took the turn found at 5 pairs only at the time offset check's 20th."""
        result = self.mount_check.result
        frame_turn = result is not None and result.frame and result.verdict == 'disagrees'
        if not self.time_offset_check.settled and not frame_turn:
            return
        with self._mount_unsaid_lock:
            unsaid, self._mount_unsaid = self._mount_unsaid, None
        if unsaid is not None:
            self._say_mount_verdict(unsaid)
        if result is None or result is self._mount_taken:
            return  # nothing new (a camera checked anew keeps the turn it has until its own verdict)
        self._mount_taken = result
        self._frame_tilt_unchecked = frame_turn and self.mount_check.config.mode == 'correct'
        if self.mount_check.config.mode != 'correct' or result.verdict != 'disagrees':
            return
        # The check read poses already turned by the correction so far: its turn adds to it.
        rotation = self._mount_correction @ self.mount_check.rotation
        self._mount_correction = rotation
        self._restart_from_ns = 0
        self.focal_check.restart()  # its pairs were posed in the told frame
        if result.frame:  # a frame convention taken: the mount's own tilt is left to fit
            self.mount_check.restart()
            if not self.time_offset_check.settled:
                self.time_offset_check.restart()  # its pairs were posed in the told frame
        self.stats.noted(
            'mount_disagrees',
            f'{result.message()}; mount_check.mode correct: every camera pose is '
            f'turned by it from now on, frame history and filter start over; {self._mount_hint(rotation)}',
        )

    def _on_mount_estimate(self, camera: PinholeCamera, estimate: MountEstimate) -> None:
        """The mount check's result (its thread), said once: now, or, before the time offset
        check has settled, by the callbacks once it has (``_take_mount_correction``). In correct
        mode the callbacks take the turn and say it then. Poses found inverted are said at once
        (:meth:`_on_inverted_poses`): no time offset makes them."""
        if estimate.verdict == 'inverted':
            self._on_inverted_poses(estimate)
            return
        with self._mount_unsaid_lock:
            if not self.time_offset_check.settled:
                self._mount_unsaid = estimate
                return
        self._say_mount_verdict(estimate)

    def _on_inverted_poses(self, estimate: MountEstimate) -> None:
        """The told poses fit the images inverted (``multiview/pose_inversion.py``): said once,
        with what to set. With ``mount_check.mode`` correct the node publishes no multi-view
        depth from the next keyframe on (``_withheld_for_inverted_poses``): triangulated with
        the inverted motion, its points would only mislead the fusion and the adaptation (the
        fusion gives the single view). Nothing is turned or inverted while running: the nodes
        after this one read the keyframe poses as published."""
        if self.pose_inverted:
            fix = 'pose_inverted is true: the source gives T_wc already, set pose_inverted: false'
        else:
            fix = 'publish T_wc, or set pose_inverted: true'
        if self.mount_check.config.mode == 'correct':
            then = '; mount_check.mode correct: no multi-view depth from now on (the fusion gives the single '
            then += 'view)'
            self._inverted_found = estimate
        else:
            then = ' (mount_check.mode correct would withhold the multi-view depth)'
        self.stats.noted('poses_inverted', f'{estimate.message()}: {fix}{then}')

    def _withheld_for_inverted_poses(self, job: Any) -> bool:
        """Whether this keyframe's multi-view depth is withheld: its poses were found inverted
        (:meth:`_on_inverted_poses`); counted. The filter's estimate of it, if it was fed before
        the verdict, is let go (frames after it are not fed: ``_on_posed_frame``)."""
        if self._inverted_found is None:
            return False
        if self.filter_feed is not None:
            self.filter_feed.discard(job.key.index)
        self.stats.noted(
            'inverted_poses_withheld',
            f'keyframe {ns_to_sec(header_stamp_ns(job)):.3f}: no multi-view depth, the told poses fit the '
            'images inverted (pose_inverted)',
        )
        return True

    def _say_mount_verdict(self, estimate: MountEstimate) -> None:
        hint = self._mount_hint(self._mount_correction @ estimate.rotation())
        self._say_verdict('mount', estimate, self.mount_check.config.mode, hint)

    def _mount_hint(self, rotation: np.ndarray) -> str:
        """The ``camera_from_pose_frame`` that holds the turn, for the user's configuration: the
        next run then starts with it (the nodes after this one hear the turn on the posing
        topics, nodes/posing.py)."""
        T = self.T_pose_cam @ rotation
        values = [*T[:3, 3], *matrix_to_quat(T[:3, :3])]
        return 'camera_from_pose_frame [' + ', '.join(f'{v:.6g}' for v in values) + '] fits'
