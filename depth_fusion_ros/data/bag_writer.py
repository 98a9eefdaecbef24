"""Writing a rosbag2 safely and in stamp order: ``AtomicBagWriter`` and ``OrderedOutput``.

A bag that looks complete must be complete (a player or an evaluation would silently use a
truncated one), so the writer only moves the bag into place once everything is written. A
converter that re-stamps messages (depth with its colour stamp) or interleaves a pose source's
own samples writes through ``OrderedOutput`` so the bag still reads in stamp order.
"""

from __future__ import annotations

import heapq
import shutil
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml
from rosbags.rosbag2 import StoragePlugin, Writer

from . import replaceable
from .rosbag_read import bag_typestore

STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}


#: ``custom_data`` of every bag this writer makes (rosbag2 metadata, version 6 on): what
#: ``overwrite`` may replace. A bag recorded on a robot has no such entry and is never replaced.
WRITTEN_BY = ('written_by', 'depth_fusion_ros')


def is_rosbag2(path: Path) -> bool:
    """Whether ``path`` is a rosbag2 folder."""
    return path.is_dir() and (path / 'metadata.yaml').is_file()


def not_written_here(path: Path) -> str | None:
    """Why ``overwrite`` must keep ``path`` (``None``: a rosbag2 this writer made, its
    metadata's ``custom_data`` holding :data:`WRITTEN_BY`)."""
    if not is_rosbag2(path):
        return 'exists and is not a rosbag2 folder'
    try:
        doc = yaml.safe_load((path / 'metadata.yaml').read_text()) or {}
    except (OSError, yaml.YAMLError):
        doc = {}
    custom = (doc.get('rosbag2_bagfile_information') or {}).get('custom_data') or {}
    if isinstance(custom, dict) and custom.get(WRITTEN_BY[0]) == WRITTEN_BY[1]:
        return None
    return (
        f"is a rosbag2 without depth-fusion's mark (custom_data {WRITTEN_BY[0]}: {WRITTEN_BY[1]} in "
        'metadata.yaml), a recording or a bag converted before the mark (remove it yourself, or '
        'choose another name)'
    )


def check_replaceable(out: Path, overwrite: bool) -> None:
    """The rule of :mod:`.replaceable` with this writer's mark: a bag recorded on a robot (or by
    ``depth-fusion run --record``) is never replaced."""
    replaceable.check_replaceable(out, overwrite, not_written_here)


class AtomicBagWriter:
    """A rosbag2 writer that only makes ``out`` appear once everything is written.

    The bag is written to ``<parent>/.<name>.<random>.partial/<name>`` and moved to ``out`` on
    a clean exit; on an exception (or Ctrl-C) the partial folder is removed. An existing
    ``out`` is an error unless ``overwrite``, and then only a bag this writer made is replaced
    (:func:`check_replaceable`).
    """

    def __init__(self, out: str | Path, storage: str = 'mcap', overwrite: bool = False) -> None:
        if storage not in STORAGES:
            raise ValueError(f'storage must be one of {", ".join(STORAGES)}, got {storage!r}')
        self.out = Path(out)
        check_replaceable(self.out, overwrite)
        self.overwrite = overwrite
        self.storage = storage
        self.typestore = bag_typestore()
        self.counts: dict[str, int] = {}
        self._connections: dict[str, Any] = {}
        self._tmp_root: Path | None = None
        self._writer: Writer | None = None

    def __enter__(self) -> AtomicBagWriter:
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self._tmp_root = Path(
            tempfile.mkdtemp(prefix=f'.{self.out.name}.', suffix='.partial', dir=self.out.parent)
        )
        try:
            self._writer = Writer(
                self._tmp_root / self.out.name, version=9, storage_plugin=STORAGES[self.storage]
            )
            self._writer.open()
            self._writer.set_custom_data(*WRITTEN_BY)
        except BaseException:
            shutil.rmtree(self._tmp_root, ignore_errors=True)
            raise
        return self

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Serialise ``msg`` (a rosbags message) and write it at ``stamp_ns``."""
        self.write_raw(topic, msgtype, stamp_ns, self.typestore.serialize_cdr(msg, msgtype))

    def write_raw(self, topic: str, msgtype: str, stamp_ns: int, data: bytes | memoryview) -> None:
        assert self._writer is not None, 'use AtomicBagWriter as a context manager'
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise ValueError(f'topic {topic} already holds {conn.msgtype}, cannot write {msgtype}')
        self._writer.write(conn, int(stamp_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        assert self._writer is not None and self._tmp_root is not None
        try:
            self._writer.close()
            if exc_type is None:
                self._publish()
        finally:
            shutil.rmtree(self._tmp_root, ignore_errors=True)

    def _publish(self) -> None:
        """Move the finished bag into place (an old bag is moved aside first, then deleted)."""
        assert self._tmp_root is not None
        if self.out.exists():
            check_replaceable(self.out, self.overwrite)  # again: it may have come while we wrote
            self.out.rename(self._tmp_root / 'replaced')
        (self._tmp_root / self.out.name).rename(self.out)


class OrderedOutput:
    """Buffers serialised messages briefly so they reach the bag in stamp order.

    A depth image is re-stamped with the colour stamp it is associated with, which can be up
    to ``horizon_ns`` earlier or later than the bag position: messages wait in a heap until
    the bag has moved ``horizon_ns`` past them (a handful of frames in memory).
    """

    def __init__(self, writer: AtomicBagWriter, horizon_ns: int) -> None:
        self.writer = writer
        self.horizon_ns = horizon_ns
        self._heap: list[tuple[int, int, str, str, bytes]] = []
        self._seq = 0

    def push(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        data = bytes(self.writer.typestore.serialize_cdr(msg, msgtype))
        heapq.heappush(self._heap, (stamp_ns, self._seq, topic, msgtype, data))
        self._seq += 1

    def advance(self, now_ns: int) -> None:
        while self._heap and self._heap[0][0] < now_ns - self.horizon_ns:
            self._pop()

    def flush(self) -> None:
        while self._heap:
            self._pop()

    def _pop(self) -> None:
        stamp, _, topic, msgtype, data = heapq.heappop(self._heap)
        self.writer.write_raw(topic, msgtype, stamp, data)
