"""``sensor_msgs/CompressedImage`` (image_transport ``compressed``) <-> RGB arrays, with OpenCV.

Most recorded robot bags hold colour as ``CompressedImage`` on ``<image topic>/compressed``
(JPEG, sometimes PNG), published by image_transport's ``compressed`` plugin. Its ``format``
field reads ``"<raw encoding>; <jpeg|png> compressed <coded encoding>"`` (e.g.
``"rgb8; jpeg compressed bgr8"``); older drivers write just ``"jpeg"``. OpenCV decodes every
variant to BGR/BGRA/grey, which is turned into the package's RGB convention here. Like
``data.messages`` this works on rclpy and rosbags messages alike (it only reads ``format``
and ``data``) and imports no ROS module.

``image_transport_for_topics`` tells from a bag's topic names whether its colour is raw or
compressed, so ``depth-fusion run`` can set ``multi_view_node.image_transport`` by itself.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .message_stamps import _header_for
from .messages import as_kind, image_msg, image_to_rgb

#: Suffix image_transport appends to the base topic for the ``compressed`` transport.
COMPRESSED_SUFFIX = '/compressed'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
TRANSPORTS = ('raw', 'compressed')
#: Formats ``compressed_image_msg`` writes. PNG is lossless (a converted evaluation bag gives
#: exactly the raw bag's results); JPEG is what robots record (~9x smaller than PNG, lossy).
FORMATS = ('png', 'jpeg')
DEFAULT_JPEG_QUALITY = 90


def compressed_topic(image_topic: str) -> str:
    """``/camera/rgb/image_color`` -> ``/camera/rgb/image_color/compressed``."""
    return image_topic.rstrip('/') + COMPRESSED_SUFFIX


def _codec(fmt: str) -> str:
    """``'jpeg'`` or ``'png'`` from a ``format`` string, or ``ValueError`` naming it."""
    text = fmt.lower()
    if 'compresseddepth' in text:
        raise ValueError(f'format {fmt!r} is compressedDepth (a depth transport), not a colour image')
    codec = text.split(';')[-1].strip().split(' ')[0] if ';' in text else text.strip()
    if codec in ('jpeg', 'jpg'):
        return 'jpeg'
    if codec == 'png':
        return 'png'
    if not codec:  # an empty format: let OpenCV sniff the bytes (it knows the magic numbers)
        return ''
    raise ValueError(f'compressed image format {fmt!r} is neither jpeg nor png')


#: ``cv2.imdecode`` flags that decode a JPEG at 1/2, 1/4, 1/8 of its size (in the DCT domain).
REDUCED_COLOUR = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}


def is_jpeg(msg: Any) -> bool:
    """Whether a CompressedImage's ``format`` names JPEG (False for anything else, bad ones included)."""
    try:
        return _codec(str(msg.format)) == 'jpeg'
    except ValueError:
        return False


def decode_compressed(msg: Any, reduce: int = 1) -> np.ndarray:
    """``HxWx3 uint8`` RGB of a CompressedImage; ``ValueError`` saying why it cannot be decoded.

    Grey images are repeated into three channels and alpha is dropped, as
    ``messages.image_to_rgb`` does for raw images. 16-bit PNGs (depth) are refused.
    ``reduce`` (2, 4 or 8): a JPEG is decoded at that fraction of its size, rounded up (a
    1296x972 JPEG: 3.9 instead of 13 ms, within a quarter of a grey level of an area resize of
    the full image); other formats and factors decode at full size.
    """
    codec = _codec(str(msg.format))
    buf = np.frombuffer(bytes(msg.data), dtype=np.uint8) if len(msg.data) else np.zeros(0, np.uint8)
    if buf.size == 0:
        raise ValueError('compressed image has no data')
    flag = REDUCED_COLOUR.get(reduce) if codec == 'jpeg' else None
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED if flag is None else flag)
    if img is None:
        raise ValueError(f'OpenCV cannot decode the {buf.size}-byte {msg.format!r} image (corrupt data?)')
    if img.dtype != np.uint8:
        raise ValueError(f'compressed image decodes to {img.dtype} (depth?), expected 8-bit colour')
    # OpenCV's conversions, not numpy copies through reversed strides: the same bytes, a
    # fiftieth of the time on a large image (docs/nodes.md, "Cameras larger than 640x480").
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def encode_compressed(rgb: np.ndarray, fmt: str = 'png', jpeg_quality: int = DEFAULT_JPEG_QUALITY) -> bytes:
    """PNG or JPEG bytes of an ``HxWx3 uint8`` RGB image (coded as bgr8, like image_transport)."""
    if fmt not in FORMATS:
        raise ValueError(f'compressed format must be one of {", ".join(FORMATS)}, got {fmt!r}')
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f'expected an HxWx3 uint8 RGB image, got {rgb.dtype} {rgb.shape}')
    if not 1 <= int(jpeg_quality) <= 100:
        raise ValueError(f'JPEG quality must be in [1, 100], got {jpeg_quality}')
    params = (
        [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == 'jpeg' else [cv2.IMWRITE_PNG_COMPRESSION, 3]
    )
    bgr = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode('.jpg' if fmt == 'jpeg' else '.png', bgr, params)
    if not ok:
        raise ValueError(f'OpenCV could not encode a {rgb.shape} image as {fmt}')
    return data.tobytes()


def compressed_image_msg(
    rgb: np.ndarray, header: Any, *, kind: Any, fmt: str = 'png', jpeg_quality: int = DEFAULT_JPEG_QUALITY
) -> Any:
    """A ``sensor_msgs/CompressedImage`` of an RGB image, ``format`` as image_transport writes it."""
    k = as_kind(kind)
    data = encode_compressed(rgb, fmt, jpeg_quality)
    return k.new(
        COMPRESSED_IMAGE,
        header=_header_for(header, k),
        format=f'rgb8; {fmt} compressed bgr8',
        data=k.uint8_array(data),
    )


def image_transport_for_topics(
    topic_names: Iterable[str], image_topic: str = '/camera/rgb/image_color'
) -> str:
    """``'raw'`` or ``'compressed'``: the transport a bag or a live graph offers ``image_topic`` on.

    Raw wins when both are there (no decoding cost, no loss); ``'raw'`` too when neither is (the
    node then reports the missing input itself).
    """
    names = set(topic_names)
    if image_topic in names:
        return 'raw'
    return 'compressed' if compressed_topic(image_topic) in names else 'raw'


@dataclass(frozen=True)
class ColourFormat:
    """How a converter writes colour: raw ``rgb8`` Image, or a CompressedImage (``png``/``jpeg``)
    on ``<topic>/compressed``."""

    compression: str | None = None
    jpeg_quality: int = DEFAULT_JPEG_QUALITY

    def __post_init__(self) -> None:
        if self.compression is not None and self.compression not in FORMATS:
            raise ValueError(
                f'compression must be one of {", ".join(FORMATS)} or None, got {self.compression!r}'
            )
        if not 1 <= int(self.jpeg_quality) <= 100:
            raise ValueError(f'JPEG quality must be in [1, 100], got {self.jpeg_quality}')

    def message(self, rgb: np.ndarray, header: Any, topic: str, *, kind: Any) -> tuple[str, str, Any]:
        """``(topic, msgtype, message)`` of one colour frame in this format."""
        if self.compression is None:
            return topic, 'sensor_msgs/msg/Image', image_msg(rgb, 'rgb8', header, kind=kind)
        msg = compressed_image_msg(
            rgb, header, kind=kind, fmt=self.compression, jpeg_quality=self.jpeg_quality
        )
        return compressed_topic(topic), COMPRESSED_IMAGE, msg


def any_image_to_rgb(msg: Any) -> np.ndarray:
    """RGB of a raw Image or a CompressedImage (readers of bags that may hold either)."""
    if hasattr(msg, 'format') and not hasattr(msg, 'encoding'):
        return decode_compressed(msg)
    return image_to_rgb(msg)


def colour_topic_in(bag_topics: Iterable[str], image_topic: str) -> str:
    """``image_topic`` if present, else its ``/compressed`` topic if that is (else ``image_topic``)."""
    return (
        compressed_topic(image_topic)
        if image_transport_for_topics(bag_topics, image_topic) == 'compressed'
        else image_topic
    )


#: Raw rgb8 colour (the converters' default).
RAW_COLOUR = ColourFormat()
