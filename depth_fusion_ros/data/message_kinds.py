"""Message kinds: how to build a message in rclpy or in a rosbags typestore, behind one interface.

rclpy messages default every field and hold ``uint8[]`` as ``array.array``; rosbags dataclasses
need every field and hold ``uint8[]`` as numpy arrays. A ``MessageKind`` hides that, so each
builder in ``messages`` has one code path for nodes (rclpy) and for the bag tools (rosbags, no
rclpy needed). rclpy is imported lazily, on first use of ``RCLPY``.
"""

from __future__ import annotations

import array
import dataclasses
import importlib
from typing import Any

import numpy as np


class MessageKind:
    """How to build messages of one flavour (rclpy or a rosbags typestore)."""

    name = 'abstract'

    def new(self, msgtype: str, **fields: Any) -> Any:
        """A message of type ``pkg/msg/Name`` with the given fields."""
        raise NotImplementedError

    def uint8_array(self, data: bytes) -> Any:
        """The value to store in a ``uint8[]`` field."""
        raise NotImplementedError

    def float64_array(self, values: np.ndarray) -> Any:
        """The value to store in a ``float64[]`` (or ``float64[N]``) field."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f'<MessageKind {self.name}>'


class RclpyKind(MessageKind):
    """rclpy message classes (``sensor_msgs.msg.Image`` ...), imported on first use."""

    name = 'rclpy'

    def __init__(self) -> None:
        self._classes: dict[str, type] = {}

    def message_class(self, msgtype: str) -> type:
        cls = self._classes.get(msgtype)
        if cls is None:
            pkg, _, name = msgtype.split('/')
            try:
                cls = getattr(importlib.import_module(f'{pkg}.msg'), name)
            except (ImportError, AttributeError) as exc:
                raise ValueError(f'rclpy message type {msgtype} is not available: {exc}') from exc
            self._classes[msgtype] = cls
        return cls

    def new(self, msgtype: str, **fields: Any) -> Any:
        return self.message_class(msgtype)(**fields)

    def uint8_array(self, data: bytes) -> Any:
        # rclpy's setter copies a bytes object in well under a millisecond for 640x480 rgb8;
        # a numpy array or memoryview goes through a per-element path (~85 ms).
        return data

    def float64_array(self, values: np.ndarray) -> Any:
        return array.array('d', np.asarray(values, dtype=np.float64).ravel().tolist())


class TypestoreKind(MessageKind):
    """rosbags dataclasses of one typestore (ROS 2 Jazzy, or ROS 1 Noetic for test bags).

    ROS 1 differences are filled in: ``Header.seq`` defaults to 0 and lower-case field
    names map onto ROS 1's upper-case ones (``CameraInfo.K``), so callers write one code path.
    """

    def __init__(self, typestore: Any) -> None:
        self.typestore = typestore
        self.name = f'rosbags:{type(typestore).__name__}'
        self._fields: dict[str, tuple[type, frozenset[str]]] = {}

    def _class(self, msgtype: str) -> tuple[type, frozenset[str]]:
        entry = self._fields.get(msgtype)
        if entry is None:
            try:
                cls = self.typestore.types[msgtype]
            except KeyError as exc:
                raise ValueError(f'message type {msgtype} is not in the typestore') from exc
            entry = (cls, frozenset(f.name for f in dataclasses.fields(cls)))
            self._fields[msgtype] = entry
        return entry

    def new(self, msgtype: str, **fields: Any) -> Any:
        cls, names = self._class(msgtype)
        args = {}
        for key, value in fields.items():
            if key not in names and key.upper() in names:
                key = key.upper()
            args[key] = value
        if 'seq' in names and 'seq' not in args:
            args['seq'] = 0
        return cls(**args)

    def uint8_array(self, data: bytes) -> Any:
        return np.frombuffer(data, dtype=np.uint8)

    def float64_array(self, values: np.ndarray) -> Any:
        return np.array(values, dtype=np.float64).ravel()


#: The rclpy message kind (lazy import: using it requires rclpy, importing this module does not).
RCLPY = RclpyKind()


def as_kind(kind: Any) -> MessageKind:
    """Accept ``RCLPY``, ``'rclpy'``, a ``MessageKind`` or a rosbags ``Typestore``."""
    if isinstance(kind, MessageKind):
        return kind
    if kind == 'rclpy':
        return RCLPY
    if hasattr(kind, 'types') and hasattr(kind, 'serialize_cdr'):
        return TypestoreKind(kind)
    raise ValueError(f'kind must be RCLPY, a MessageKind or a rosbags Typestore, got {kind!r}')
