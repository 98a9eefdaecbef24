"""The colour encodings real cameras publish: packed YUV 4:2:2, semi-planar YUV (nv21 4:2:0,
nv24 4:4:4), Bayer mosaics, 16-bit colour.

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


# --------------------------------------------------------------------------- semi-planar YUV

PLANAR = ('nv21', 'nv24')


def _planes(y: np.ndarray, u: np.ndarray, v: np.ndarray, encoding: str, step: int = 0) -> bytes:
    """The wire bytes of per-pixel Y, U, V as ``encoding``, every row padded to ``step`` (0xAB).

    ``nv21``: the Y rows, then one row of V U pairs per two Y rows, each pair the mean of a 2x2
    block; rows of ``step`` bytes. ``nv24``: the Y rows, then one row of U V pairs per Y row, every
    pixel its own; chroma rows of ``2 * step`` bytes (V4L2's NV24)."""
    h, w = y.shape
    step = step or w
    if encoding == 'nv21':
        blocks = [c.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3)) for c in (v, u)]
        chroma, chroma_step = np.stack(blocks, axis=-1).reshape(h // 2, w), step
    else:
        chroma, chroma_step = np.stack((u, v), axis=-1).reshape(h, 2 * w), 2 * step

    def rows(plane: np.ndarray, stride: int) -> bytes:
        out = np.full((plane.shape[0], stride), 0xAB, np.uint8)
        out[:, : plane.shape[1]] = np.clip(np.rint(plane), 0, 255)
        return out.tobytes()

    return rows(y, step) + rows(chroma, chroma_step)


def _planar_msg(data: bytes, encoding: str, width: int, height: int, step: int = 0, kind=TYPESTORE):
    """A ``sensor_msgs/Image`` of ``encoding`` holding ``data`` (image_msg builds no planar YUV)."""
    msg = _msg(np.frombuffer(data, np.uint8).reshape(1, -1), 'mono8', kind)
    msg.encoding, msg.width, msg.height, msg.step = encoding, width, height, step or width
    return msg


@pytest.mark.parametrize('encoding', PLANAR)
def test_planar_yuv_known_values(encoding):
    # BT.601 limited range, as the yuv422 test: black, white, red, green, blue and a mid grey
    known = {(16, 128, 128): (0, 0, 0), (235, 128, 128): (255, 255, 255), (81, 90, 240): (255, 0, 0)}
    known.update({(145, 54, 34): (0, 255, 0), (41, 240, 110): (0, 0, 255), (126, 128, 128): (128,) * 3})
    for (y, u, v), colour in known.items():
        data = _planes(*(np.full((2, 2), c, float) for c in (y, u, v)), encoding)
        out = m.image_to_rgb(_planar_msg(data, encoding, 2, 2))
        assert _max_error(out, np.full((2, 2, 3), colour)) <= 2, ((y, u, v), out[0, 0])


@pytest.mark.parametrize('kind', KINDS, ids=KIND_IDS)
@pytest.mark.parametrize('image', list(IMAGES))
@pytest.mark.parametrize('encoding', PLANAR)
def test_planar_yuv_decodes_to_the_source_colours(kind, image, encoding):
    rgb = IMAGES[image]()
    out = m.image_to_rgb(_planar_msg(_planes(*_yuv(rgb), encoding), encoding, W, H, kind=kind))
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    # flat, and nv24 (a chroma sample per pixel): YUV rounding only; nv21 gradient: plus the 2x2
    # block's shared chroma, half a pixel off each (R and B change 4 and 2 a pixel across, B 1 down)
    assert _max_error(out, rgb) <= (4 if image == 'gradient' and encoding == 'nv21' else 2)


def test_nv24_keeps_a_chroma_sample_per_pixel():
    """Random colours, every pixel its own: nv24 gives them back to rounding, nv21 cannot."""
    rgb = np.random.default_rng(3).integers(0, 256, (H, W, 3), dtype=np.uint8)
    errors = {}
    for encoding in PLANAR:
        out = m.image_to_rgb(_planar_msg(_planes(*_yuv(rgb), encoding), encoding, W, H))
        errors[encoding] = _max_error(out, rgb)
    assert errors['nv24'] <= 2 and errors['nv21'] > 50, errors


def test_planar_chroma_orders_are_told_apart():
    """nv21's chroma pairs are V U, nv24's U V: the other order gives the wrong colour."""
    rgb = _flat()
    y, u, v = _yuv(rgb)
    for encoding in PLANAR:
        right = _planar_msg(_planes(y, u, v, encoding), encoding, W, H)
        swapped = _planar_msg(_planes(y, v, u, encoding), encoding, W, H)
        assert _max_error(m.image_to_rgb(right), rgb) <= 2, encoding
        assert _max_error(m.image_to_rgb(swapped), rgb) > 50, encoding


@pytest.mark.parametrize('encoding', PLANAR)
@pytest.mark.parametrize('pad', [2, 7])
def test_planar_yuv_row_padding_is_dropped(encoding, pad):
    """``step`` counts the Y rows' bytes, padding included; nv24's chroma rows are twice that."""
    yuv = _yuv(_gradient())
    expected = m.image_to_rgb(_planar_msg(_planes(*yuv, encoding), encoding, W, H))
    padded = _planar_msg(_planes(*yuv, encoding, step=W + pad), encoding, W, H, step=W + pad)
    np.testing.assert_array_equal(m.image_to_rgb(padded), expected)


@pytest.mark.parametrize(('width', 'height'), [(5, 4), (4, 3), (5, 3)])
def test_nv21_odd_size_raises_one_line(width, height):
    msg = _planar_msg(bytes(width * height * 2), 'nv21', width, height)
    with pytest.raises(ValueError, match=f'nv21 .*must be even, got {width}x{height}') as exc:
        m.image_to_rgb(msg)
    assert '\n' not in str(exc.value)
    with pytest.raises(InputError, match=f'must be even, got {width}x{height}') as exc:
        decode_colour(msg)
    assert exc.value.reason == 'bad_image'
    # 4:4:4 shares no chroma: nv24 of any size is fine
    nv24 = _planar_msg(bytes(width * height * 3), 'nv24', width, height)
    assert m.image_to_rgb(nv24).shape == (height, width, 3)


@pytest.mark.parametrize(('encoding', 'formula'), [('nv21', '3/2'), ('nv24', '3')])
def test_planar_yuv_step_and_size_are_checked(encoding, formula):
    data = _planes(*_yuv(_gradient()), encoding, step=W + 2)
    expected = (W + 2) * H * (3 if encoding == 'nv24' else 1.5)
    assert len(data) == expected
    msg = _planar_msg(data, encoding, W, H, step=W - 1)
    with pytest.raises(ValueError, match=f'step 31 is smaller than a {encoding} row of 32 pixels'):
        m.image_to_rgb(msg)
    for size in (len(data) - 1, len(data) + 1, (W + 2) * H, 2 * (W + 2) * H):  # short, long, other layouts
        msg = _planar_msg(data[:size].ljust(size, b'\0'), encoding, W, H, step=W + 2)
        with pytest.raises(ValueError) as exc:
            m.image_to_rgb(msg)
        message = str(exc.value)
        assert '\n' not in message and encoding in message
        assert (
            f'has {size} bytes, expected step*height*{formula} = 34*24*{formula} = {int(expected)}' in message
        )
        with pytest.raises(InputError) as exc:
            decode_colour(msg)
        assert exc.value.reason == 'bad_image'
    # no array of pixels: image_to_numpy and image_msg say where they are read
    with pytest.raises(ValueError, match=f'{encoding} is planar YUV.*image_to_rgb'):
        m.image_to_numpy(_planar_msg(data, encoding, W, H, step=W + 2))
    with pytest.raises(ValueError, match=f'{encoding} is planar YUV'):
        _msg(np.zeros((H, W), np.uint8), encoding)


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
    assert set(PLANAR) <= set(COLOUR_ENCODINGS)
    for encoding, size in (('nv21', W * H * 3 // 2), ('nv24', W * H * 3)):
        data = np.random.default_rng(2).integers(0, 256, size, dtype=np.uint8).tobytes()
        out = decode_colour(
            _planar_msg(data, encoding, W, H, kind=m.RCLPY if m.RCLPY in KINDS else TYPESTORE)
        )
        assert out.shape == (H, W, 3) and out.dtype == np.uint8, encoding


def test_nodes_refuse_other_encodings():
    for encoding in ('32FC1', '16UC1'):
        with pytest.raises(InputError) as exc:
            decode_colour(_msg(np.zeros((H, W), m.ENCODINGS[encoding][0]), encoding))
        assert exc.value.reason == 'bad_encoding'
        message = str(exc.value)
        assert '\n' not in message and f"'{encoding}' is not colour" in message
        assert 'yuv422' in message and 'bayer_rggb8' in message and 'rgb16' in message
        assert 'nv21' in message and 'nv24' in message
    odd = _msg(np.zeros((4, 5, 2), np.uint8), 'yuv422')
    with pytest.raises(InputError, match='width must be even, got 5') as exc:
        decode_colour(odd)
    assert exc.value.reason == 'bad_image'
