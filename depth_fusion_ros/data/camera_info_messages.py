"""``sensor_msgs/CameraInfo`` <-> ``CameraCalibration``: ROI and binning, K/P checks, builder.

Readers accept ROS 1 messages decoded by rosbags too (``CameraInfo.K``/``D`` upper case).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..camera import PinholeCamera
from .camera_info_geometry import ImageWindow
from .message_kinds import as_kind
from .message_stamps import _header_for
from .undistort import CameraCalibration


def _field(msg: Any, name: str) -> Any:
    """``msg.name``, or ROS 1's upper-case ``msg.NAME``."""
    if hasattr(msg, name):
        return getattr(msg, name)
    return getattr(msg, name.upper())


def _field_or(msg: Any, name: str, default: Any) -> Any:
    """``_field(msg, name)``, or ``default`` where the message has no such field."""
    try:
        return _field(msg, name)
    except AttributeError:
        return default


def camera_info_window(msg: Any) -> ImageWindow:
    """The ROI and binning of a ``CameraInfo`` (REP 104), checked against its sensor size.

    ROS 1 and ROS 2 both spell ``binning_x``, ``binning_y`` and ``roi`` in lower case; a message
    without them (a hand-built stand-in) is the full sensor, unbinned.
    """
    roi = _field_or(msg, 'roi', None)
    return ImageWindow.of(
        int(msg.width),
        int(msg.height),
        binning_x=_field_or(msg, 'binning_x', 0),
        binning_y=_field_or(msg, 'binning_y', 0),
        x_offset=_field_or(roi, 'x_offset', 0),
        y_offset=_field_or(roi, 'y_offset', 0),
        roi_width=_field_or(roi, 'width', 0),
        roi_height=_field_or(roi, 'height', 0),
    )


def _projection(msg: Any, name: str, columns: int, what: str, fix: str) -> np.ndarray:
    """CameraInfo's K (3x3) or P (3x4) as a flat array, or a one-line ``ValueError``: wrong
    size, a size of zero, a non-finite value or a focal length that is not positive."""
    width, height = int(msg.width), int(msg.height)
    values = np.asarray(_field(msg, name), dtype=np.float64).ravel()
    if values.size != 3 * columns:
        raise ValueError(f'CameraInfo {name.upper()} has {values.size} values, expected {3 * columns}')
    fx, fy = values[0], values[columns + 1]
    if width <= 0 or height <= 0 or not np.all(np.isfinite(values)) or fx <= 0 or fy <= 0:
        raise ValueError(
            f'CameraInfo {what} (size {width}x{height}, {name.upper()} = {values.tolist()}): {fix}'
        )
    return values


def camera_info_to_calibration(msg: Any, *, rectified: bool = False) -> CameraCalibration:
    """``CameraCalibration`` (K at the size of the published image, distortion model, D) of a
    ``CameraInfo``.

    Binning and the region of interest are applied as REP 104 / image_geometry do
    (``camera_info_geometry``): the camera is that of the ROI, binned, and D is unchanged.
    ``rectified=True`` reads an image that is already rectified (image_proc's ``image_rect``,
    published with the raw image's camera_info): the intrinsics are P's ``fx = P[0]``,
    ``fy = P[5]``, ``cx = P[2]``, ``cy = P[6]`` (binning and ROI applied the same way) and there is
    no distortion (``plumb_bob``, ``D = ()``); K and D are not used.
    """
    if rectified:
        P = _projection(msg, 'p', 4, 'P is not set', 'a rectified image needs the rectified intrinsics in P')
        camera = camera_info_window(msg).camera(P[0], P[5], P[2], P[6])
        return CameraCalibration(camera, 'plumb_bob', ())
    K = _projection(
        msg, 'k', 3, 'is not calibrated', 'set the intrinsics parameter or publish a calibrated camera_info'
    )
    D = tuple(np.asarray(_field(msg, 'd'), dtype=np.float64).ravel().tolist())
    camera = camera_info_window(msg).camera(K[0], K[4], K[2], K[5])
    return CameraCalibration(camera, str(msg.distortion_model), D)


def camera_info_msg(
    camera: PinholeCamera | CameraCalibration,
    header: Any,
    *,
    kind: Any,
    distortion_model: str | None = None,
    D: np.ndarray | tuple[float, ...] | None = None,
) -> Any:
    """A ``sensor_msgs/CameraInfo``: K, D, R = I, P = [K | 0], no binning, full ROI.

    ``camera`` is a ``CameraCalibration`` (its model and D are used unless overridden) or an
    undistorted ``PinholeCamera`` (``plumb_bob`` with zero D by default).
    """
    k = as_kind(kind)
    if isinstance(camera, CameraCalibration):
        model = camera.distortion_model if distortion_model is None else distortion_model
        coeffs = camera.D if D is None else D
        cam = camera.camera
    else:
        cam = camera
        model = 'plumb_bob' if distortion_model is None else distortion_model
        coeffs = (0.0,) * 5 if D is None else D
    K = cam.K
    P = np.hstack((K, np.zeros((3, 1))))
    roi = k.new(
        'sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return k.new(
        'sensor_msgs/msg/CameraInfo',
        header=_header_for(header, k),
        height=cam.height,
        width=cam.width,
        distortion_model=model,
        d=k.float64_array(np.asarray(coeffs, dtype=np.float64)),
        k=np.asarray(K, dtype=np.float64).ravel(),
        r=np.eye(3).ravel(),
        p=P.ravel(),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
