"""The ``header.stamp`` of a message read and patched in its raw CDR bytes, without deserializing.

Why: the replayer never deserializes a message (the bag's bytes go straight to the wire), yet a
looped replay must move every header stamp forward by the bag's length so downstream pose
buffers and time sources see time moving forward; the recorder reads the same stamp to log
arrival against stamp. A message that starts with a ``std_msgs/Header`` has its stamp at byte 4
(after the 4-byte CDR encapsulation header), so both are a ``struct`` unpack / pack. No ROS
import: the message definitions are rosbags' Jazzy type store.
"""

from __future__ import annotations

import functools
import struct
from typing import Any


@functools.lru_cache(maxsize=1)
def _jazzy_typestore() -> Any:
    """rosbags' Jazzy type store, built once: building it takes about 0.2 s, and a recorder
    asked for it once per topic at start."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def has_leading_header(msgtype: str) -> bool:
    """Whether the message starts with a ``std_msgs/Header`` (so its stamp sits at byte 4)."""
    try:
        fields = _jazzy_typestore().fielddefs[msgtype][1]
    except KeyError:
        return False
    return bool(fields) and fields[0][1][1] == 'std_msgs/msg/Header'


def header_stamp_ns(raw: bytes | memoryview) -> int:
    """``header.stamp`` in ns of a CDR message that starts with a Header (no deserialization)."""
    endian = '<' if raw[1] & 1 else '>'
    sec, nanosec = struct.unpack_from(f'{endian}iI', raw, 4)
    return sec * 1_000_000_000 + nanosec


def shift_header_stamp(raw: bytes, shift_ns: int) -> bytes:
    """A copy of ``raw`` whose ``header.stamp`` is moved by ``shift_ns`` (for looped playback)."""
    if shift_ns == 0:
        return raw
    endian = '<' if raw[1] & 1 else '>'
    sec, nanosec = divmod(header_stamp_ns(raw) + shift_ns, 1_000_000_000)
    out = bytearray(raw)
    struct.pack_into(f'{endian}iI', out, 4, sec, nanosec)
    return bytes(out)
