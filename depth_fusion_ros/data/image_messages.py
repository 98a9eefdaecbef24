"""``sensor_msgs/Image`` <-> numpy: encodings, pixels, RGB (incl. YUV and Bayer), depth, builders.

Readers only read attributes, so they accept rclpy and rosbags messages (ROS 1 ones too);
builders take a message kind (``message_kinds``).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from .message_kinds import as_kind
from .message_stamps import _header_for

_U8, _U16 = np.dtype(np.uint8), np.dtype(np.uint16)

#: encoding -> (numpy dtype, channels). The packed YUV 4:2:2 encodings are 2 uint8 channels per
#: pixel (a pair of pixels shares one U and one V); Bayer mosaics are 1 channel.
ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    'rgb8': (_U8, 3),
    'bgr8': (_U8, 3),
    'rgba8': (_U8, 4),
    'bgra8': (_U8, 4),
    'mono8': (_U8, 1),
    '8UC1': (_U8, 1),
    '8UC3': (_U8, 3),
    'rgb16': (_U16, 3),
    'bgr16': (_U16, 3),
    'rgba16': (_U16, 4),
    'bgra16': (_U16, 4),
    'mono16': (_U16, 1),
    '16UC1': (_U16, 1),
    '32FC1': (np.dtype(np.float32), 1),
    # packed YUV 4:2:2: ROS 2 Jazzy's names (uyvy, yuyv) and the deprecated ones cameras still use
    'uyvy': (_U8, 2),
    'yuv422': (_U8, 2),
    'yuyv': (_U8, 2),
    'yuv422_yuy2': (_U8, 2),
    'bayer_rggb8': (_U8, 1),
    'bayer_bggr8': (_U8, 1),
    'bayer_gbrg8': (_U8, 1),
    'bayer_grbg8': (_U8, 1),
    'bayer_rggb16': (_U16, 1),
    'bayer_bggr16': (_U16, 1),
    'bayer_gbrg16': (_U16, 1),
    'bayer_grbg16': (_U16, 1),
}

#: Semi-planar YUV (sensor_msgs' nv21 and nv24, as camera_ros/libcamera, GStreamer and ffmpeg
#: publish them): a full-resolution Y plane of ``height`` rows of ``step`` bytes, then one plane
#: of interleaved chroma. nv21 is 4:2:0, V U byte pairs in height/2 rows of ``step`` bytes (width
#: and height even); nv24 is 4:4:4, U V byte pairs (V4L2's and ffmpeg's NV24, NV42 is V U) in
#: ``height`` rows of ``2 * step`` bytes. No per-pixel array, so not in ``ENCODINGS``:
#: ``image_to_rgb`` reads them. The data is ``step * height * 3/2`` (nv21) or ``* 3`` (nv24) bytes
#: (sensor_msgs' numChannels/getHeightScaling, 2 and 1 for nv24, do not add up to its 3 bytes a
#: pixel; this is V4L2's layout, which camera_ros copies from libcamera's buffer with its stride).
PLANAR_YUV = ('nv21', 'nv24')


def _encoding(encoding: str) -> tuple[np.dtype, int]:
    try:
        return ENCODINGS[encoding]
    except KeyError:
        if encoding in PLANAR_YUV:
            raise ValueError(
                f'{encoding} is planar YUV, not an array of pixels: image_to_rgb reads it'
            ) from None
        raise ValueError(
            f'unsupported image encoding {encoding!r} (supported: {", ".join(ENCODINGS)})'
        ) from None


def image_to_numpy(msg: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` as ``(H, W)`` or ``(H, W, C)``, native byte order.

    Honours ``step`` (row padding) and ``is_bigendian``. The result may be a read-only view
    of the message buffer: copy it before writing into it.
    """
    dtype, channels = _encoding(msg.encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    if height < 0 or width < 0:
        raise ValueError(f'image size {width}x{height} is negative')
    if step < row_bytes:
        raise ValueError(
            f'image step {step} is smaller than a {msg.encoding} row of {width} pixels ({row_bytes} B)'
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8) if len(msg.data) else np.zeros(0, np.uint8)
    if buf.size != step * height:
        raise ValueError(
            f'image data has {buf.size} bytes, expected step*height = {step}*{height} = {step * height}'
        )
    rows = buf.reshape(height, step)[:, :row_bytes]
    wire = dtype.newbyteorder('>' if msg.is_bigendian else '<') if dtype.itemsize > 1 else dtype
    if not rows.flags.c_contiguous:
        rows = np.ascontiguousarray(rows)
    arr = rows.view(wire)
    arr = arr.reshape(height, width, channels) if channels > 1 else arr.reshape(height, width)
    if wire != dtype.newbyteorder('='):
        arr = arr.astype(dtype.newbyteorder('='))
    return arr


#: ``cv2.cvtColor`` code to RGB of every colour encoding (``None``: the samples are RGB already).
#: A 16-bit encoding uses the code of its 8-bit twin after ``>> 8``.
#: yuv422 is ROS's name for UYVY (bytes U Y0 V Y1), yuv422_yuy2 for YUYV (Y0 U Y1 V); OpenCV
#: decodes both as BT.601 limited range (Y 16..235), as the V4L2 drivers produce them.
#: ROS names a Bayer pattern by its first 2x2 block (bayer_rggb8: R at row 0, column 0), OpenCV
#: by the block starting at the second row and column, so bayer_rggb8 is ``BayerBG`` (as in
#: cv_bridge; test_camera_encodings checks every pattern on a mosaic of known colours).
_TO_RGB: dict[str, int | None] = {
    'rgb8': None,
    '8UC3': None,
    'rgb16': None,
    'bgr8': cv2.COLOR_BGR2RGB,
    'bgr16': cv2.COLOR_BGR2RGB,
    'rgba8': cv2.COLOR_RGBA2RGB,
    'rgba16': cv2.COLOR_RGBA2RGB,
    'bgra8': cv2.COLOR_BGRA2RGB,
    'bgra16': cv2.COLOR_BGRA2RGB,
    'mono8': cv2.COLOR_GRAY2RGB,
    '8UC1': cv2.COLOR_GRAY2RGB,
    'mono16': cv2.COLOR_GRAY2RGB,
    'uyvy': cv2.COLOR_YUV2RGB_UYVY,
    'yuv422': cv2.COLOR_YUV2RGB_UYVY,
    'yuyv': cv2.COLOR_YUV2RGB_YUY2,
    'yuv422_yuy2': cv2.COLOR_YUV2RGB_YUY2,
    'bayer_rggb8': cv2.COLOR_BayerBG2RGB,
    'bayer_rggb16': cv2.COLOR_BayerBG2RGB,
    'bayer_bggr8': cv2.COLOR_BayerRG2RGB,
    'bayer_bggr16': cv2.COLOR_BayerRG2RGB,
    'bayer_gbrg8': cv2.COLOR_BayerGR2RGB,
    'bayer_gbrg16': cv2.COLOR_BayerGR2RGB,
    'bayer_grbg8': cv2.COLOR_BayerGB2RGB,
    'bayer_grbg16': cv2.COLOR_BayerGB2RGB,
}

#: The colour encodings ``image_to_rgb`` accepts.
COLOUR_ENCODINGS = (*_TO_RGB, *PLANAR_YUV)

_PACKED_YUV = frozenset(('uyvy', 'yuv422', 'yuyv', 'yuv422_yuy2'))

#: BT.601 limited range (Y 16..235, U and V 16..240 around 128) to RGB as a ``cv2.transform``
#: matrix (columns Y, U, V, 1), for nv24: OpenCV has no NV24 code, and its 4:4:4
#: ``COLOR_YUV2RGB`` is the full-range analogue-YUV formula, which would give nv24 other colours
#: than the same camera's nv21 or yuv422. These are the coefficients of OpenCV's own
#: ``COLOR_YUV2RGB_NV21``/``_YUY2``/``_UYVY`` (ITUR_BT_601_CY ... in 2**-20), the conversion
#: cv_bridge uses for yuv422, so every YUV encoding decodes alike (to +-1 of rounding).
_CY, _CUB, _CUG, _CVG, _CVR = (c / 2**20 for c in (1220542, 2116026, -409993, -852492, 1673527))
_BT601_TO_RGB = np.array(
    [
        [_CY, 0.0, _CVR, -16 * _CY - 128 * _CVR],
        [_CY, _CUG, _CVG, -16 * _CY - 128 * (_CUG + _CVG)],
        [_CY, _CUB, 0.0, -16 * _CY - 128 * _CUB],
    ]
)


def _planar_yuv_to_rgb(msg: Any) -> np.ndarray:
    """RGB of an nv21 or nv24 image (``PLANAR_YUV``), row padding (``step > width``) dropped."""
    enc = msg.encoding
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height < 0 or width < 0:
        raise ValueError(f'image size {width}x{height} is negative')
    if enc == 'nv21' and (width % 2 or height % 2):
        raise ValueError(
            f'nv21 shares chroma in 2x2 blocks: width and height must be even, got {width}x{height}'
        )
    if step < width:
        raise ValueError(f'image step {step} is smaller than a {enc} row of {width} pixels ({width} B)')
    buf = np.frombuffer(msg.data, dtype=np.uint8) if len(msg.data) else np.zeros(0, np.uint8)
    luma = step * height
    expected, formula = (luma * 3 // 2, '*3/2') if enc == 'nv21' else (luma * 3, '*3')
    if buf.size != expected:
        raise ValueError(
            f'image data has {buf.size} bytes, expected step*height{formula} = {step}*{height}{formula} = '
            f'{expected} ({enc})'
        )
    if buf.size == 0:
        return np.zeros((height, width, 3), dtype=np.uint8)
    if enc == 'nv21':
        # the Y rows, then the height/2 V U rows, all of ``step`` bytes: OpenCV's (H*3/2, W) layout
        planes = buf.reshape(height * 3 // 2, step)[:, :width]
        return cv2.cvtColor(np.ascontiguousarray(planes), cv2.COLOR_YUV2RGB_NV21)
    y = buf[:luma].reshape(height, step)[:, :width]
    uv = buf[luma:].reshape(height, 2 * step)[:, : 2 * width].reshape(height, width, 2)
    # Y below 16 counts as 16 (black), as in OpenCV's YUV decoders; cv2.merge, not np.dstack
    # (4 instead of 24 ms for 1920x1080)
    yuv = cv2.merge((cv2.max(y, 16), uv))
    return cv2.transform(yuv, _BT601_TO_RGB)


def image_to_rgb(msg: Any) -> np.ndarray:
    """An ``HxWx3 uint8`` RGB image of any encoding in ``COLOUR_ENCODINGS`` (contiguous copy).

    Grey is repeated into three channels and alpha dropped. Packed YUV 4:2:2 (uyvy/yuv422,
    yuyv/yuv422_yuy2) and semi-planar YUV (nv21 4:2:0, nv24 4:4:4; ``PLANAR_YUV``) are
    converted from BT.601 limited range; packed YUV needs an even width, nv21 an even width and
    height. Bayer mosaics are demosaiced bilinearly. 16-bit encodings (rgb16, bgr16, rgba16,
    bgra16, mono16, bayer_*16, either byte order) keep their high byte: ``v >> 8``, truncating,
    so 8-bit values scaled by 257 come back exactly; a camera that puts 10 or 12 bits in the low
    bits of a 16-bit word comes out dark.
    """
    enc = msg.encoding
    if enc in PLANAR_YUV:
        return _planar_yuv_to_rgb(msg)
    if enc in _PACKED_YUV and int(msg.width) % 2:
        raise ValueError(f'{enc} packs pixels in pairs: the width must be even, got {int(msg.width)}')
    arr = image_to_numpy(msg)
    if enc not in _TO_RGB:
        raise ValueError(f'cannot make an RGB image from encoding {enc!r}')
    if arr.dtype == np.uint16:
        arr = (arr >> 8).astype(np.uint8)
    code = _TO_RGB[enc]
    if code is None:
        return np.ascontiguousarray(arr)
    if arr.size == 0:
        return np.zeros((*arr.shape[:2], 3), dtype=np.uint8)
    # OpenCV's channel swap, not a numpy copy through a reversed stride: the same bytes,
    # 0.2 ms instead of 12.5 ms for a 1296x972 bgr8 image (a 30 Hz camera's callback budget).
    return cv2.cvtColor(np.ascontiguousarray(arr), code)


def image_to_depth(msg: Any) -> np.ndarray:
    """Depth in metres (float32, NaN = none) from 32FC1 (m) or 16UC1/mono16 (mm, REP 118).

    Non-finite and non-positive depths become NaN (REP 117's ``±Inf`` carry no depth).
    """
    arr = image_to_numpy(msg)
    if msg.encoding == '32FC1':
        depth = np.array(arr, dtype=np.float32)
    elif msg.encoding in ('16UC1', 'mono16'):
        depth = arr.astype(np.float32) / 1000.0
    else:
        raise ValueError(f'a depth image must be 32FC1 or 16UC1, got {msg.encoding!r}')
    with np.errstate(invalid='ignore'):
        depth[~(depth > 0) | ~np.isfinite(depth)] = np.nan
    return depth


def image_msg(arr: np.ndarray, encoding: str, header: Any, *, kind: Any, bigendian: bool = False) -> Any:
    """A ``sensor_msgs/Image`` holding ``arr`` (no row padding).

    ``arr`` must have the dtype and channel count of ``encoding`` (``float64`` is accepted for
    ``32FC1`` and cast). ``bigendian=True`` writes multi-byte pixels big-endian.
    """
    k = as_kind(kind)
    dtype, channels = _encoding(encoding)
    arr = np.asarray(arr)
    if encoding == '32FC1' and arr.dtype == np.float64:
        arr = arr.astype(np.float32)
    shape_ok = arr.ndim == 2 if channels == 1 else (arr.ndim == 3 and arr.shape[2] == channels)
    if channels == 1 and arr.ndim == 3 and arr.shape[2] == 1:
        arr, shape_ok = arr[..., 0], True
    if not shape_ok:
        want = '(H, W)' if channels == 1 else f'(H, W, {channels})'
        raise ValueError(f'{encoding} needs an array of shape {want}, got {arr.shape}')
    if arr.dtype != dtype:
        raise ValueError(f'{encoding} needs dtype {dtype}, got {arr.dtype}')
    wire = dtype.newbyteorder('>' if bigendian else '<') if dtype.itemsize > 1 else dtype
    data = np.ascontiguousarray(arr, dtype=wire).tobytes()
    height, width = arr.shape[:2]
    return k.new(
        'sensor_msgs/msg/Image',
        header=_header_for(header, k),
        height=int(height),
        width=int(width),
        encoding=encoding,
        is_bigendian=int(bool(bigendian and dtype.itemsize > 1)),
        step=int(width * channels * dtype.itemsize),
        data=k.uint8_array(data),
    )


def rgb_image_msg(rgb: np.ndarray, header: Any, *, kind: Any) -> Any:
    """``rgb8`` image of an ``HxWx3 uint8`` RGB array."""
    return image_msg(rgb, 'rgb8', header, kind=kind)


def depth_image_msg(depth: np.ndarray, header: Any, *, kind: Any) -> Any:
    """``32FC1`` image of a depth array in metres (NaN = none, REP 117)."""
    return image_msg(np.asarray(depth, dtype=np.float32), '32FC1', header, kind=kind)
