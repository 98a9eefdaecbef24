"""The colour encodings real cameras publish: packed YUV 4:2:2, Bayer mosaics, 16-bit colour.

Every test builds the wire bytes from a known RGB image (or known Y/U/V values) itself, so the
OpenCV codes in ``messages.image_to_rgb`` are checked against the encodings' definitions, not
against their names.
"""

from __future__ import annotations

import numpy as np
import pytest
from message_kinds import KIND_IDS, KINDS, TYPESTORE

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.nodes.image_input import COLOUR_ENCODINGS, InputError, decode_colour

H, W = 24, 32
FLAT = (200, 100, 30)


def _flat(colour=FLAT) -> np.ndarray:
    rgb = np.empty((H, W, 3), np.uint8)
    rgb[:] = colour
    return rgb


def _gradient() -> np.ndarray:
    """Every channel linear in x and y (R 40..164, G 30..99, B 115..200)."""
    y, x = np.mgrid[0:H, 0:W]
    return np.stack((40 + 4 * x, 30 + 3 * y, 200 - 2 * x - y), axis=-1).astype(np.uint8)


IMAGES = {'flat': _flat, 'gradient': _gradient}


def _msg(arr: np.ndarray, encoding: str, kind=TYPESTORE, bigendian: bool = False):
    return m.image_msg(arr, encoding, m.header_msg(1_000, 'cam', kind=kind), kind=kind, bigendian=bigendian)


def _max_error(a: np.ndarray, b: np.ndarray) -> int:
    return int(np.abs(a.astype(np.int32) - b.astype(np.int32)).max())


# --------------------------------------------------------------------------- Bayer

BAYER = ('rggb', 'bggr', 'gbrg', 'grbg')


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic of ``rgb`` as ROS defines ``bayer_<pattern>``: the pattern's letters are
    the colours at (row 0, col 0), (0, 1), (1, 0), (1, 1) of every 2x2 block."""
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for letter, (dy, dx) in zip(pattern, ((0, 0), (0, 1), (1, 0), (1, 1)), strict=True):
        out[dy::2, dx::2] = rgb[dy::2, dx::2, 'rgb'.index(letter)]
    return out


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize('image', list(IMAGES))
@pytest.mark.parametrize('pattern', BAYER)
def test_bayer8_demosaics_to_the_source_colours(kind, image, pattern):
    rgb = IMAGES[image]()
    out = m.image_to_rgb(_msg(_mosaic(rgb, pattern), f'bayer_{pattern}8', kind))
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    # interior pixels: bilinear demosaicing of a flat or linear image is exact up to rounding
    assert _max_error(out[2:-2, 2:-2], rgb[2:-2, 2:-2]) <= 2


@pytest.mark.parametrize('pattern', BAYER)
def test_bayer_patterns_are_told_apart(pattern):
    """A mosaic read as any other pattern gives the wrong colour: the test above can fail."""
    mosaic = _mosaic(_flat(), pattern)
    for other in BAYER:
        out = m.image_to_rgb(_msg(mosaic, f'bayer_{other}8'))
        error = _max_error(out[2:-2, 2:-2], _flat()[2:-2, 2:-2])
        assert (error <= 1) == (other == pattern), (pattern, other, out[4, 4])


@pytest.mark.parametrize('bigendian', [False, True])
@pytest.mark.parametrize('pattern', BAYER)
def test_bayer16_is_the_high_byte_demosaiced(pattern, bigendian):
    rgb = _gradient()
    noise = np.random.default_rng(0).integers(0, 256, rgb.shape[:2]).astype(np.uint16)
    mosaic16 = (_mosaic(rgb, pattern).astype(np.uint16) << 8) | noise  # the low byte is dropped
    msg = _msg(mosaic16, f'bayer_{pattern}16', bigendian=bigendian)
    assert bool(msg.is_bigendian) == bigendian
    out = m.image_to_rgb(msg)
    np.testing.assert_array_equal(out, m.image_to_rgb(_msg(_mosaic(rgb, pattern), f'bayer_{pattern}8')))
    assert _max_error(out[2:-2, 2:-2], rgb[2:-2, 2:-2]) <= 2


# --------------------------------------------------------------------------- packed YUV 4:2:2


def _yuv(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BT.601 limited-range Y, U, V (floats) of ``rgb`` (what a V4L2 camera sends)."""
    r, g, b = (rgb[..., i].astype(np.float64) for i in range(3))
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    return y, u, v


def _pack(y: np.ndarray, u: np.ndarray, v: np.ndarray, layout: str) -> np.ndarray:
    """``(H, W, 2) uint8`` of per-pixel Y, U, V: each pair of pixels shares its mean U and V.

    ``uyvy`` (ROS yuv422) bytes are U Y0 V Y1, ``yuyv`` (ROS yuv422_yuy2) Y0 U Y1 V."""
    u2 = (u[:, 0::2] + u[:, 1::2]) / 2
    v2 = (v[:, 0::2] + v[:, 1::2]) / 2
    out = np.empty((*y.shape, 2), np.float64)
    luma, chroma = (1, 0) if layout == 'uyvy' else (0, 1)
    out[..., luma] = y
    out[:, 0::2, chroma] = u2
    out[:, 1::2, chroma] = v2
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


YUV = {'yuv422': 'uyvy', 'uyvy': 'uyvy', 'yuv422_yuy2': 'yuyv', 'yuyv': 'yuyv'}


@pytest.mark.parametrize('encoding', list(YUV))
def test_yuv422_known_values(encoding):
    # black then white in one pair (U = V = 128): the luma bytes are where the layout says
    pair = _pack(np.array([[16.0, 235.0]]), np.full((1, 2), 128.0), np.full((1, 2), 128.0), YUV[encoding])
    np.testing.assert_array_equal(m.image_to_rgb(_msg(pair, encoding)), [[[0, 0, 0], [255, 255, 255]]])
    # BT.601 limited-range red, green, blue and a mid grey
    known = {(81, 90, 240): (255, 0, 0), (145, 54, 34): (0, 255, 0), (41, 240, 110): (0, 0, 255)}
    known[(126, 128, 128)] = (128, 128, 128)
    for (y, u, v), colour in known.items():
        pair = _pack(*(np.full((1, 2), c, float) for c in (y, u, v)), YUV[encoding])
        out = m.image_to_rgb(_msg(pair, encoding))
        assert _max_error(out, np.array([[colour, colour]])) <= 2, ((y, u, v), out[0, 0])


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize('image', list(IMAGES))
@pytest.mark.parametrize('encoding', list(YUV))
def test_yuv422_decodes_to_the_source_colours(kind, image, encoding):
    rgb = IMAGES[image]()
    out = m.image_to_rgb(_msg(_pack(*_yuv(rgb), YUV[encoding]), encoding, kind))
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    # flat: YUV rounding only; gradient: plus the pair's shared chroma (R and B change 4 and 2 a pixel)
    assert _max_error(out, rgb) <= (2 if image == 'flat' else 4)


def test_uyvy_and_yuyv_are_told_apart():
    rgb = _flat()
    packed = _pack(*_yuv(rgb), 'uyvy')
    assert _max_error(m.image_to_rgb(_msg(packed, 'yuv422')), rgb) <= 2
    assert _max_error(m.image_to_rgb(_msg(packed, 'yuv422_yuy2')), rgb) > 50


@pytest.mark.parametrize('encoding', list(YUV))
def test_yuv422_odd_width_raises_one_line(encoding):
    msg = _msg(np.zeros((4, 5, 2), np.uint8), encoding)
    with pytest.raises(ValueError, match=f'{encoding} .*width must be even, got 5') as exc:
        m.image_to_rgb(msg)
    assert '\n' not in str(exc.value)


def test_yuv422_step_and_size_are_checked():
    packed = _pack(*_yuv(_gradient()), 'uyvy')
    msg = _msg(packed, 'yuv422')
    msg.step = 2 * W - 2
    with pytest.raises(ValueError, match='step 62 is smaller than a yuv422 row of 32 pixels'):
        m.image_to_rgb(msg)
    msg = _msg(packed, 'yuv422')
    msg.height = H + 1
    with pytest.raises(ValueError, match='expected step\\*height'):
        m.image_to_rgb(msg)


@pytest.mark.parametrize(('encoding', 'arr'), [('yuv422', 'packed'), ('bayer_grbg8', 'mosaic')])
def test_row_padding_is_honoured(encoding, arr):
    rgb = _gradient()
    data = _pack(*_yuv(rgb), 'uyvy') if arr == 'packed' else _mosaic(rgb, 'grbg')
    msg = _msg(data, encoding)
    rows = np.frombuffer(bytes(msg.data), np.uint8).reshape(H, msg.step)
    padded = np.hstack((rows, np.full((H, 6), 0xAB, np.uint8)))
    expected = m.image_to_rgb(msg)
    msg.step += 6
    msg.data = padded.ravel()
    np.testing.assert_array_equal(m.image_to_rgb(msg), expected)


# --------------------------------------------------------------------------- 16-bit colour


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize('bigendian', [False, True])
@pytest.mark.parametrize('encoding', ['rgb16', 'bgr16', 'rgba16', 'bgra16', 'mono16'])
def test_16bit_colour_keeps_the_high_byte(kind, bigendian, encoding):
    rgb = _gradient()
    rng = np.random.default_rng(1)
    if encoding == 'mono16':
        rgb = np.repeat(rgb[..., :1], 3, axis=-1)
    channels = {'rgb16': rgb, 'bgr16': rgb[..., ::-1], 'mono16': rgb[..., 0]}
    alpha = np.full((H, W, 1), 9, np.uint8)
    channels['rgba16'] = np.concatenate((rgb, alpha), axis=-1)
    channels['bgra16'] = np.concatenate((rgb[..., ::-1], alpha), axis=-1)
    high = channels[encoding].astype(np.uint16)
    wide = (high << 8) | rng.integers(0, 256, high.shape).astype(np.uint16)  # v >> 8 truncates
    msg = _msg(wide, encoding, kind, bigendian=bigendian)
    assert bool(msg.is_bigendian) == bigendian
    out = m.image_to_rgb(msg)
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    np.testing.assert_array_equal(out, rgb)
    # 8-bit values scaled by 257 (0 -> 0, 255 -> 65535) come back exactly
    np.testing.assert_array_equal(m.image_to_rgb(_msg(high * 257, encoding, kind, bigendian=bigendian)), rgb)


def test_mono16_depth_is_unchanged():
    mm = np.array([[0, 1000], [2500, 65535]], np.uint16)
    np.testing.assert_allclose(
        m.image_to_depth(_msg(mm, 'mono16')), [[np.nan, 1.0], [2.5, 65.535]], rtol=1e-6
    )


# --------------------------------------------------------------------------- the nodes' input

NEW = (
    'rgb16', 'bgr16', 'rgba16', 'bgra16', 'mono16', 'uyvy', 'yuv422', 'yuyv', 'yuv422_yuy2',
    *(f'bayer_{p}{bits}' for p in BAYER for bits in (8, 16)),
)  # fmt: skip


def test_nodes_accept_the_camera_encodings():
    assert set(NEW) <= set(COLOUR_ENCODINGS)
    assert set(COLOUR_ENCODINGS) == set(m.COLOUR_ENCODINGS)
    for encoding in NEW:
        dtype, channels = m.ENCODINGS[encoding]
        shape = (H, W) if channels == 1 else (H, W, channels)
        arr = np.random.default_rng(2).integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
        out = decode_colour(_msg(arr, encoding, m.RCLPY if m.RCLPY in KINDS else TYPESTORE))
        assert out.shape == (H, W, 3) and out.dtype == np.uint8, encoding


def test_nodes_refuse_other_encodings():
    for encoding in ('32FC1', '16UC1'):
        with pytest.raises(InputError) as exc:
            decode_colour(_msg(np.zeros((H, W), m.ENCODINGS[encoding][0]), encoding))
        assert exc.value.reason == 'bad_encoding'
        message = str(exc.value)
        assert '\n' not in message and f"'{encoding}' is not colour" in message
        assert 'yuv422' in message and 'bayer_rggb8' in message and 'rgb16' in message
    odd = _msg(np.zeros((4, 5, 2), np.uint8), 'yuv422')
    with pytest.raises(InputError, match='width must be even, got 5') as exc:
        decode_colour(odd)
    assert exc.value.reason == 'bad_image'
