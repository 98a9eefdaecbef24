"""The multi-view node's image path per frame (``depth-fusion bench --only image_input``).

Every posed camera image costs the node a decode, an undistortion and a resize to the working
grid in its callback, at the camera's rate, before any depth work: at 30 Hz a 27 ms path
was 80 % of a core (docs/performance.md, "A four-keyframe queue in the multi-view node, and
cameras larger than 640x480"). This times ``CameraInput.working_image`` on real
``sensor_msgs`` messages (raw ``bgr8`` and JPEG ``CompressedImage``) of a distorted camera at
the sizes users' cameras have, for the 320x240 working grid.
"""

from __future__ import annotations

import numpy as np

from . import BenchOptions, BenchRow, load_note, median_seconds

TITLE = 'image path per frame (decode, undistort, resize to 320x240; CameraInput.working_image)'

#: (width, height) of the cameras timed: VGA (the datasets; not box-filtered), 720p (a
#: RealSense colour stream) and 1296x972 (ScanNet-like), both box-filtered by 2.
SIZES = ((640, 480), (1280, 720), (1296, 972))
#: TUM fr1's distortion (plumb_bob), scaled with the image: every size is undistorted.
DISTORTION = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


def _picture(width: int, height: int) -> np.ndarray:
    """A smooth test picture with some noise (its JPEG decodes at the slow end of a camera's)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:height, 0:width]
    base = np.dstack([xx * 255 // max(1, width - 1), yy * 255 // max(1, height - 1), (xx + yy) % 256])
    noise = rng.integers(0, 24, (height, width, 3))
    return np.clip(base + noise, 0, 255).astype(np.uint8)


def _messages(width: int, height: int) -> tuple[object, object, object]:
    """A CameraInfo, a raw bgr8 Image and a JPEG CompressedImage of one camera."""
    from ..camera import PinholeCamera
    from ..data import messages
    from ..data.compressed import compressed_image_msg
    from ..data.undistort import CameraCalibration

    kind = messages.RCLPY
    header = messages.header_msg(1, 'camera', kind=kind)
    vga = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3)  # TUM fr1's colour camera
    info = messages.camera_info_msg(
        CameraCalibration(vga.scaled(width, height), 'plumb_bob', DISTORTION), header, kind=kind
    )
    rgb = _picture(width, height)
    raw = messages.image_msg(np.ascontiguousarray(rgb[..., ::-1]), 'bgr8', header, kind=kind)
    jpeg = compressed_image_msg(rgb, header, kind=kind, fmt='jpeg')
    return info, raw, jpeg


def run(opts: BenchOptions) -> list[BenchRow]:
    """Milliseconds per ``working_image`` call (median), raw and JPEG, at each of ``SIZES`` (one thread:
    OpenCV's own, the node's callback thread)."""
    from ..nodes.image_input import CameraInput

    repeats = 3 if opts.quick else max(20, 4 * opts.repeats)
    sizes = SIZES[:1] + SIZES[-1:] if opts.quick else SIZES
    rows: list[BenchRow] = []
    for width, height in sizes:
        info, raw, jpeg = _messages(width, height)
        camera = CameraInput(320, 240)
        camera.update(info)
        for label, msg in (('bgr8', raw), ('JPEG', jpeg)):
            # the first call builds (and caches) the undistortion maps: warm-up
            seconds = median_seconds(lambda c=camera, m=msg: c.working_image(m), repeats)
            name = f'{width}x{height} {label}: image -> working grid'
            rows.append(BenchRow(name, seconds * 1e3, 'ms', load_note(f'median of {repeats} calls')))
    return rows
