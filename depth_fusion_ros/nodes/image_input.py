"""Incoming messages -> checked arrays on the working grid, or an :class:`InputError` saying why not.

Every way a message can be unusable (wrong encoding, an image whose size does not match its
camera_info, no camera_info yet, a NaN or non-unit quaternion; a stamp that goes backwards
or repeats, in ``stamp_guard.py``) becomes an ``InputError`` (``input_error.py``) carrying a
short *reason* key. The node counts the drop
under that key and warns (throttled per key), so one broken stream neither kills the node
nor floods the log, and the counters say exactly what was wrong.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..camera import PinholeCamera
from ..data import messages
from ..data.compressed import decode_compressed, is_jpeg
from ..data.lens_correction import add_radial, can_add_radial
from ..data.undistort import CameraCalibration, Undistorter, check_distortion
from ..geometry import PoseError
from .input_error import InputError
from .params import ParamSpec

#: Encodings ``messages.image_to_rgb`` turns into RGB: rgb8, bgr8, rgba8, bgra8, mono8, 8UC1, 8UC3,
#: the 16-bit rgb16, bgr16, rgba16, bgra16, mono16, packed YUV 4:2:2 (uyvy/yuv422, yuyv/yuv422_yuy2),
#: semi-planar YUV nv21 (4:2:0) and nv24 (4:4:4) and Bayer bayer_*8/16, what USB (usb_cam,
#: v4l2_camera), embedded (camera_ros / libcamera) and industrial (Spinnaker, Arena, pylon) camera
#: drivers publish.
COLOUR_ENCODINGS = messages.COLOUR_ENCODINGS


@dataclass(frozen=True)
class WorkingImage:
    """One image on the working grid: undistorted RGB, its camera, and the source header."""

    stamp_ns: int
    rgb: np.ndarray
    camera: PinholeCamera
    header: Any


def header_stamp_ns(msg: Any) -> int:
    """Integer nanoseconds of ``msg.header.stamp`` (exact, the key used to pair keyframes)."""
    return messages.stamp_to_ns(msg.header.stamp)


def calibration_from_parameters(intrinsics: list[float], distortion: list[float]) -> tuple[float, ...] | None:
    """``(fx, fy, cx, cy)`` when the intrinsics parameter is set (any value non-zero), else ``None``."""
    if not any(intrinsics):
        return None
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    if fx <= 0 or fy <= 0:
        raise ValueError(f'parameter camera_intrinsics: fx and fy must be positive, got {intrinsics}')
    check_distortion('plumb_bob', tuple(distortion))
    return fx, fy, cx, cy


def working_grid_parameters(note: str = '') -> tuple[ParamSpec, ...]:
    """``width``, ``height``, ``camera_intrinsics``, ``camera_distortion``, ``camera_rectified``:
    the working grid, the fallback calibration and how camera_info is read, for every node that
    reads camera images (``note`` is appended to the calibration descriptions)."""
    return (
        ParamSpec(
            'width', 320, 'working grid width (pixels): images are undistorted and resized to it', 16, 4096
        ),
        ParamSpec('height', 240, 'working grid height (pixels)', 16, 4096),
        ParamSpec(
            'camera_intrinsics',
            [0.0, 0.0, 0.0, 0.0],
            'fx, fy, cx, cy at the raw image size, used instead of camera_info when set '
            f'(all zero: use camera_info){note}',
            length=4,
        ),
        ParamSpec(
            'camera_distortion',
            [0.0, 0.0, 0.0, 0.0, 0.0],
            f'plumb_bob k1, k2, p1, p2, k3 for camera_intrinsics{note}',
            length=5,
        ),
        ParamSpec(
            'camera_rectified',
            False,
            "the camera images are already rectified (image_proc's image_rect topics): intrinsics "
            "from camera_info's P, its distortion ignored; false: raw images, undistorted with K "
            f'and D{note}',
        ),
    )


class CameraInput:
    """Keeps the latest CameraInfo and turns colour images into the undistorted working grid.

    ``fixed_intrinsics`` (``fx, fy, cx, cy`` at the raw image size) and ``fixed_distortion``
    replace CameraInfo for sources that publish none. With ``rectified=True`` the images are
    already undistorted (e.g. the keyframe topic), so a CameraInfo is not needed: the image is
    only resized to the working grid if its size differs.

    ``camera_rectified=True`` is another thing: the images are image_proc's ``image_rect``, and
    their CameraInfo (the raw camera's, D non-zero) is read with
    ``camera_info_to_calibration(..., rectified=True)``: intrinsics from P, no undistortion.
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        rectified: bool = False,
        fixed_intrinsics: tuple[float, ...] | None = None,
        fixed_distortion: tuple[float, ...] = (),
        camera_rectified: bool = False,
    ) -> None:
        self.width = int(width)
        self.height = int(height)
        self.rectified = rectified
        self.camera_rectified = bool(camera_rectified)
        self.fixed_intrinsics = fixed_intrinsics
        self.fixed_distortion = tuple(fixed_distortion)
        self.calibration: CameraCalibration | None = None
        self._sensor_size: tuple[int, int] | None = None
        #: A radial lens distortion the calibration does not hold, added to it once the focal
        #: length check has fitted it (``data/lens_correction.py``; 0: none). Set by
        #: ``multi_view_node`` (``focal_check.mode`` correct).
        self.lens_k1 = 0.0
        #: The raw size of the last image undistorted: what the calibration in use is published
        #: at (``lens_topic.py``; camera_info's own size where there is one).
        self.raw_size: tuple[int, int] | None = None

    @classmethod
    def from_parameters(cls, params: dict[str, Any], rectified: bool = False) -> CameraInput:
        """Built from the values of :func:`working_grid_parameters`."""
        return cls(
            int(params['width']),
            int(params['height']),
            rectified=rectified,
            fixed_intrinsics=calibration_from_parameters(
                params['camera_intrinsics'], params['camera_distortion']
            ),
            fixed_distortion=tuple(params['camera_distortion']),
            camera_rectified=bool(params.get('camera_rectified', False)),
        )

    def update(self, info_msg: Any) -> None:
        """Take a CameraInfo (raises ``InputError('bad_camera_info')`` if it is unusable)."""
        try:
            calib = messages.camera_info_to_calibration(info_msg, rectified=self.camera_rectified)
            check_distortion(calib.distortion_model, calib.D)
        except ValueError as exc:
            raise InputError('bad_camera_info', f'camera_info: {exc}') from None
        self.calibration = calib
        #: The size camera_info gives before its binning and ROI, where they change it (REP 104):
        #: an image of that size means a driver that binned or cropped K itself (said on a mismatch).
        sensor = (int(info_msg.width), int(info_msg.height))
        self._sensor_size = sensor if sensor != (calib.camera.width, calib.camera.height) else None

    def can_correct_lens(self) -> bool:
        """Whether a radial lens correction can be added to the calibration the images are
        undistorted with (not a fisheye model; the fixed calibration is plumb_bob)."""
        calib = self.calibration
        return self.fixed_intrinsics is not None or (calib is not None and can_add_radial(calib))

    def told_distorted(self) -> bool:
        """Whether the calibration told (the fixed one, or camera_info's) has a distortion of
        its own, which a lens correction adds to."""
        if self.fixed_intrinsics is not None:
            return any(d != 0.0 for d in self.fixed_distortion)
        return self.calibration is not None and self.calibration.is_distorted

    def calibration_in_use(self) -> CameraCalibration | None:
        """The calibration raw images are undistorted with now (the told one and ``lens_k1``),
        at the raw size; None before there is one (no camera_info, or fixed intrinsics and no
        image yet) or on rectified input."""
        if self.rectified:
            return None
        calib = self.calibration
        size = (calib.camera.width, calib.camera.height) if calib is not None else self.raw_size
        if size is None:
            return None
        try:
            return self._calibration_for(*size)
        except InputError:
            return None

    def _calibration_for(self, width: int, height: int) -> CameraCalibration:
        return add_radial(self._told_calibration_for(width, height), self.lens_k1)

    def _told_calibration_for(self, width: int, height: int) -> CameraCalibration:
        if self.fixed_intrinsics is not None:
            fx, fy, cx, cy = self.fixed_intrinsics
            return CameraCalibration(
                PinholeCamera(width, height, fx, fy, cx, cy), 'plumb_bob', self.fixed_distortion
            )
        calib = self.calibration
        if calib is None:
            if self.rectified:
                return _identity_calibration(width, height)
            raise InputError(
                'no_camera_info', 'no camera_info received yet (set camera_intrinsics if there is none)'
            )
        if (calib.camera.width, calib.camera.height) != (width, height):
            said = f'{calib.camera.width}x{calib.camera.height}'
            if self._sensor_size == (width, height):
                said += (
                    f" after its binning and ROI (REP 104: width, height and K are the full sensor's; "
                    f"the image has camera_info's own {width}x{height}: a driver that binned or cropped "
                    'K itself should publish binning 0 and an empty ROI)'
                )
            raise InputError('size_mismatch', f'image is {width}x{height} but camera_info says {said}')
        return calib

    def working_image(self, msg: Any) -> WorkingImage:
        """Decode, undistort and resize an image message (Image or CompressedImage) to the working grid."""
        reduced = self._reduced_jpeg(msg)
        if reduced is not None:
            small, undistorter = reduced
            rgb = undistorter.rgb_from_shrunk(small)
        else:
            raw = decode_colour(msg)
            height, width = raw.shape[:2]
            if width == 0 or height == 0:
                raise InputError('bad_image', 'image is empty')
            calib = self._calibration_for(width, height)
            undistorter = Undistorter.for_calibration(calib, self.width, self.height)
            rgb = undistorter.rgb(raw)
            self.raw_size = (width, height)
        return WorkingImage(header_stamp_ns(msg), np.ascontiguousarray(rgb), undistorter.camera, msg.header)

    def _reduced_jpeg(self, msg: Any) -> tuple[np.ndarray, Undistorter] | None:
        """A JPEG of a camera_info camera three times the working grid or more, decoded straight
        at the size its undistorter box-filters to (JPEG's own reduced decoding), with that
        undistorter; None where that does not apply (raw, PNG, fixed intrinsics, no camera_info
        yet, a size the camera_info does not describe): the full decode then says what is wrong."""
        calib = self.calibration
        if not _is_compressed(msg) or calib is None or self.fixed_intrinsics is not None or not is_jpeg(msg):
            return None
        undistorter = Undistorter.for_calibration(add_radial(calib, self.lens_k1), self.width, self.height)
        k = undistorter.shrink
        if k == 1 or calib.camera.width % k or calib.camera.height % k:
            return None
        small = decode_colour(msg, reduce=k)
        if small.shape[1::-1] != undistorter.shrunk_size:  # not this camera's size: said by the full decode
            return None
        return small, undistorter


def _is_compressed(msg: Any) -> bool:
    """A ``CompressedImage`` (it has ``format`` and no ``encoding``)."""
    return hasattr(msg, 'format') and not hasattr(msg, 'encoding')


def decode_colour(msg: Any, reduce: int = 1) -> np.ndarray:
    """RGB of a ``sensor_msgs/Image`` or ``CompressedImage`` (it has ``format``), or ``InputError``:
    ``bad_encoding`` / ``bad_image`` for raw images, ``bad_compressed`` for undecodable ones.
    ``reduce``: a JPEG is decoded at that fraction of its size (``decode_compressed``)."""
    if _is_compressed(msg):
        try:
            return decode_compressed(msg, reduce)
        except ValueError as exc:
            raise InputError('bad_compressed', f'compressed image: {exc}') from None
    if msg.encoding not in COLOUR_ENCODINGS:
        raise InputError(
            'bad_encoding',
            f'image encoding {msg.encoding!r} is not colour (expected {", ".join(COLOUR_ENCODINGS)})',
        )
    try:
        return messages.image_to_rgb(msg)
    except ValueError as exc:
        raise InputError('bad_image', f'image: {exc}') from None


def _identity_calibration(width: int, height: int) -> CameraCalibration:
    """A stand-in camera for already-rectified images when only resizing is needed (no K used)."""
    f = float(max(width, height))
    return CameraCalibration(
        PinholeCamera(width, height, f, f, (width - 1) / 2, (height - 1) / 2), 'plumb_bob', ()
    )


def pose_from_message(msg: Any) -> np.ndarray:
    """4x4 pose of a PoseStamped, PoseWithCovarianceStamped, Odometry or TransformStamped, or
    ``InputError('bad_pose')`` naming the problem."""
    try:
        return messages.pose_message_to_matrix(msg)
    except PoseError as exc:
        raise InputError('bad_pose', f'pose: {exc}') from None


def depth_from_message(msg: Any, what: str) -> np.ndarray:
    """A 32FC1 image as float32 (NaN kept), or ``InputError('bad_encoding')``."""
    if msg.encoding != '32FC1':
        raise InputError('bad_encoding', f'{what}: expected 32FC1, got {msg.encoding!r}')
    try:
        return np.array(messages.image_to_numpy(msg), dtype=np.float32)
    except ValueError as exc:
        raise InputError('bad_image', f'{what}: {exc}') from None
