"""A radial lens distortion the calibration does not hold, taken into it once the focal length
check has fitted it (``multiview/lens_fit.py``).

Why: a camera used without its lens calibration (camera_info with zero ``D``) feeds the
multi-view depth images whose points sit off their pinhole rays by a shift that grows with the
cube of their distance from the centre. Under rotation the filter reads that shift as parallax:
the lens stress case's multi-view MAE is 3.5-4x a pinhole lens's and the fusion keeps little of
its gain (docs/fusion.md, "A lens camera_info does not describe"). The check's fitted ``k1`` is
plumb_bob's first coefficient in normalised coordinates, so it holds at any image size: added to
the calibration's ``D``, the images are undistorted by the same OpenCV maps as a calibrated
camera's (``data/undistort.py``), and the depth downstream is that of a pinhole camera.

``multi_view_node`` takes it into its camera input (``nodes/image_input.py``); ``evaluate``
undistorts a loaded sequence's images and ground truth with it (:func:`undistort_sequence`).
"""

from __future__ import annotations

import dataclasses

from .sequence import Sequence
from .undistort import CameraCalibration, Undistorter

#: Distortion models the radial term can be added to (plumb_bob's ``k1`` is ``D[0]`` in both);
#: ``equidistant`` (fisheye) models the lens otherwise. A calibration without distortion takes
#: it whatever its model is called.
RADIAL_MODELS = ('plumb_bob', 'rational_polynomial')


def can_add_radial(calib: CameraCalibration) -> bool:
    """Whether a radial ``k1`` can be added to ``calib``'s distortion (not a fisheye model)."""
    return calib.distortion_model in RADIAL_MODELS or not calib.is_distorted


def add_radial(calib: CameraCalibration, k1: float) -> CameraCalibration:
    """``calib`` with ``k1`` added to its radial coefficient: ``D`` [k1, 0, 0, 0, 0] (plumb_bob)
    where it had none. Raises ``ValueError`` for a model it cannot be added to."""
    if k1 == 0.0:
        return calib
    if not can_add_radial(calib):
        raise ValueError(f'a radial k1 cannot be added to the {calib.distortion_model!r} distortion model')
    if not calib.is_distorted:
        return CameraCalibration(calib.camera, 'plumb_bob', (k1, 0.0, 0.0, 0.0, 0.0))
    D = list(calib.D)
    D[0] += k1
    return CameraCalibration(calib.camera, calib.distortion_model, tuple(D))


def undistort_sequence(sequence: Sequence, k1: float) -> Sequence:
    """``sequence`` seen through a pinhole lens: every image, and the ground truth (nearest, so
    no depth is blended across an edge), undistorted by a radial ``k1``. The images are already
    on the working grid (``Sequence.camera``), the ground truth on its own (``gt_camera``); the
    normalised ``k1`` holds on both."""
    gt_camera = sequence.gt_camera or sequence.camera
    rgb, depth = (
        Undistorter.for_calibration(add_radial(CameraCalibration(camera), k1), *camera.size)
        for camera in (sequence.camera, gt_camera)
    )
    frames = [
        dataclasses.replace(
            f, rgb=rgb.rgb(f.rgb), depth=None if f.depth is None else depth.depth(f.depth), _gray=None
        )
        for f in sequence.frames
    ]
    return dataclasses.replace(sequence, frames=frames)
