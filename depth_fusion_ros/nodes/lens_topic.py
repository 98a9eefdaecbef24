"""The lens the multi-view node took, told to the nodes that undistort a raw camera themselves.

``multi_view_node`` (``focal_check.mode`` correct) adds a radial ``k1`` it fitted to the
calibration it undistorts with (``data/lens_correction.py``). Its keyframe images are then a
pinhole camera's. A node that reads the raw camera itself, ``single_view_node`` with
``input_rectified: false``, kept undistorting with the told calibration: its depth was of the
lens's image while the keyframe's was of the pinhole one, and nothing said so.

So the multi-view node publishes the calibration it now undistorts with, as the camera_info the
camera should have published (its K and size, D with the ``k1`` added), on
``depth_fusion/calibration/camera_info``, stamped with the first image undistorted that way and
latched: a node that joins later still hears it. :class:`LensFollower` takes it from that
image on. It takes the radial term only, and only where the rest of the calibration is its own:
a node told another calibration (other D, another model) says so once and keeps its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from sensor_msgs.msg import CameraInfo

from ..data import messages
from ..data.lens_correction import RADIAL_MODELS
from ..data.undistort import CameraCalibration
from .image_input import CameraInput
from .qos import latched_qos

TOPIC_LENS_CAMERA_INFO = 'depth_fusion/calibration/camera_info'
#: Calibrations the topic keeps for a node that joins later: a lens is taken at most a few times.
KEPT = 4
#: Coefficients other than ``k1`` that differ by more than this are another calibration.
SAME_COEFFICIENT = 1e-9


def lens_qos() -> Any:
    return latched_qos(KEPT)


def lens_info_msg(calibration: CameraCalibration, stamp_ns: int, frame_id: str) -> Any:
    """The camera_info ``calibration`` is, stamped with the first image undistorted with it."""
    header = messages.header_msg(stamp_ns, frame_id, kind=messages.RCLPY)
    return messages.camera_info_msg(calibration, header, kind=messages.RCLPY)


def _padded(D: tuple[float, ...], n: int) -> np.ndarray:
    """``D`` with zeros to ``n`` coefficients (plumb_bob's five; an empty D is no distortion)."""
    d = np.zeros(n)
    d[: len(D)] = np.asarray(D, dtype=np.float64)
    return d


@dataclass(frozen=True)
class _Told:
    stamp_ns: int
    model: str
    D: tuple[float, ...]


class LensFollower:
    """For a node that undistorts a raw camera (``camera_input``): the ``k1`` the multi-view
    node took, added to ``camera_input.lens_k1`` from the image it was taken at on.

    Call :meth:`before_image` with each image's stamp before undistorting it. Counts and says
    (``node.stats.noted``) ``lens_followed`` when it takes one, ``lens_not_followed`` when the
    calibration differs from this node's by more than ``k1``."""

    def __init__(self, node: Any, camera_input: CameraInput) -> None:
        self._node = node
        self._camera_input = camera_input
        self._pending: list[_Told] = []
        node.subscribe(CameraInfo, TOPIC_LENS_CAMERA_INFO, self._on_info, lens_qos())

    def _on_info(self, msg: Any) -> None:
        told = _Told(messages.stamp_to_ns(msg.header.stamp), str(msg.distortion_model), tuple(msg.d))
        self._pending = sorted([*self._pending, told], key=lambda t: t.stamp_ns)

    def before_image(self, stamp_ns: int) -> None:
        """Take every calibration stamped at or before this image (the latest decides)."""
        due = [t for t in self._pending if t.stamp_ns <= stamp_ns]
        if not due:
            return
        own = self._own_distortion()
        if own is None:
            return  # no calibration of its own yet: kept until there is one
        self._pending = [t for t in self._pending if t.stamp_ns > stamp_ns]
        self._take(due[-1], *own)

    def _own_distortion(self) -> tuple[str, tuple[float, ...]] | None:
        inp = self._camera_input
        if inp.fixed_intrinsics is not None:
            return 'plumb_bob', inp.fixed_distortion
        if inp.calibration is None:
            return None
        return inp.calibration.distortion_model, inp.calibration.D

    def _take(self, told: _Told, own_model: str, own_D: tuple[float, ...]) -> None:
        n = max(5, len(told.D), len(own_D))
        theirs, ours = _padded(told.D, n), _padded(own_D, n)
        radial = told.model in RADIAL_MODELS and (own_model in RADIAL_MODELS or not np.any(ours))
        if not radial or np.any(np.abs(theirs[1:] - ours[1:]) > SAME_COEFFICIENT):
            self._node.stats.noted(
                'lens_not_followed',
                f'{TOPIC_LENS_CAMERA_INFO} says {told.model} D {np.round(theirs, 4).tolist()} from '
                f"{messages.ns_to_sec(told.stamp_ns):.3f} s on, which differs from this node's "
                f'{own_model} D {np.round(ours, 4).tolist()} by more than a radial k1: this node keeps '
                'its own calibration (give both nodes the same camera_info)',
            )
            return
        k1 = float(theirs[0] - ours[0])
        if k1 == self._camera_input.lens_k1:
            return
        self._camera_input.lens_k1 = k1
        self._node.stats.noted(
            'lens_followed',
            f'the multi-view node took a lens: k1 {k1:+.3f} added to the calibration this node '
            f'undistorts with, from the image stamped {messages.ns_to_sec(told.stamp_ns):.3f} s on '
            f'({TOPIC_LENS_CAMERA_INFO})',
        )
