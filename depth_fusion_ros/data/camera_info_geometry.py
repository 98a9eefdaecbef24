"""The image a CameraInfo describes after binning and a region of interest (REP 104).

A ``CameraInfo``'s ``width``, ``height``, K, D and P describe the full calibrated sensor. The
published image is the region of interest ``roi`` (``x_offset``, ``y_offset``, ``width``,
``height`` in full-sensor pixels; a width or height of 0 means the whole sensor in that
direction) reduced by ``binning_x`` x ``binning_y`` (0 or 1: no binning). As image_geometry's
``PinholeCameraModel``, the image is then ``roi.width / binning_x`` x ``roi.height / binning_y``
and its focal lengths are ``fx / binning_x``, ``fy / binning_y``. The distortion coefficients
act on normalised coordinates, so D is unchanged with the adjusted K.

The principal point follows the package's pixel convention (``PinholeCamera``: ``(0, 0)`` is
the *centre* of the top-left pixel, as OpenCV and ``PinholeCamera.scaled`` take it). Binned
pixel ``j`` averages full-sensor ROI pixels ``j*b .. j*b + b - 1``, whose centre is
``j*b + (b - 1) / 2``; a full-sensor coordinate ``u`` therefore lies at
``(u - x_offset + 0.5) / b - 0.5`` in the binned image, and

    cx' = (cx - x_offset + 0.5) / binning_x - 0.5,    cy' = (cy - y_offset + 0.5) / binning_y - 0.5

(the same as cropping the ROI and then ``PinholeCamera.scaled``). image_geometry writes
``(cx - x_offset) / binning_x``, which is the same without binning and ``(b - 1) / (2 b)``
pixels larger with it (0.25 px at 2x2): the corner-at-integer convention. No ROS import here:
the caller reads the message fields.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..camera import PinholeCamera


@dataclass(frozen=True)
class ImageWindow:
    """The part of the sensor an image shows: an ROI in full-sensor pixels, then binned."""

    x_offset: int
    y_offset: int
    roi_width: int
    roi_height: int
    binning_x: int = 1
    binning_y: int = 1

    @classmethod
    def of(
        cls,
        sensor_width: int,
        sensor_height: int,
        *,
        binning_x: int = 0,
        binning_y: int = 0,
        x_offset: int = 0,
        y_offset: int = 0,
        roi_width: int = 0,
        roi_height: int = 0,
    ) -> ImageWindow:
        """The window of CameraInfo values (REP 104's zeros included), or a one-line ``ValueError``
        naming the field that is wrong."""
        values = {
            'binning_x': binning_x,
            'binning_y': binning_y,
            'roi.x_offset': x_offset,
            'roi.y_offset': y_offset,
            'roi.width': roi_width,
            'roi.height': roi_height,
        }
        n = {name: _count(name, value) for name, value in values.items()}
        bx, by = max(n['binning_x'], 1), max(n['binning_y'], 1)
        x0, w = _span('x', int(sensor_width), n['roi.x_offset'], n['roi.width'])
        y0, h = _span('y', int(sensor_height), n['roi.y_offset'], n['roi.height'])
        if w % bx:
            raise ValueError(f'CameraInfo binning_x {bx} does not divide the ROI width {w}')
        if h % by:
            raise ValueError(f'CameraInfo binning_y {by} does not divide the ROI height {h}')
        return cls(x0, y0, w, h, bx, by)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the published image."""
        return self.roi_width // self.binning_x, self.roi_height // self.binning_y

    def camera(self, fx: float, fy: float, cx: float, cy: float) -> PinholeCamera:
        """The published image's camera, of the full-sensor ``fx, fy, cx, cy`` (module docstring):
        the ROI's crop, then binning as a resize (``PinholeCamera.cropped`` and ``.scaled``; an
        unbinned window is not resized, so its principal point stays ``c - offset`` exactly)."""
        roi = PinholeCamera(self.roi_width, self.roi_height, float(fx), float(fy), float(cx), float(cy))
        roi = roi.cropped(self.x_offset, self.y_offset, self.roi_width, self.roi_height)
        if (self.binning_x, self.binning_y) == (1, 1):
            return roi
        return roi.scaled(*self.size)


def _count(name: str, value: object) -> int:
    """``value`` as a non-negative ``int``, or a ``ValueError`` naming the field."""
    try:
        number = int(value)  # type: ignore[call-overload]
        whole = number == value
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole or number < 0:
        raise ValueError(f'CameraInfo {name} must be a non-negative integer, got {value!r}')
    return number


def _span(axis: str, sensor: int, offset: int, size: int) -> tuple[int, int]:
    """``(offset, size)`` of the ROI along one axis; a size of 0 is the whole sensor."""
    dim = 'width' if axis == 'x' else 'height'
    if size == 0:
        if offset != 0:
            raise ValueError(
                f'CameraInfo roi.{axis}_offset is {offset} with roi.{dim} 0 (0 means the whole sensor)'
            )
        return 0, sensor
    if offset + size > sensor:
        raise ValueError(
            f'CameraInfo roi.{dim} {size} at roi.{axis}_offset {offset} ends outside the sensor '
            f'({dim} {sensor})'
        )
    return offset, size
