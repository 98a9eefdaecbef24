"""Reading a truncated rosbag2 (a recorder that crashed) up to its last readable message.

Why: a recorder killed mid-run leaves an mcap without its footer and summary, or a sqlite3
file cut in the middle of a page, often without ``metadata.yaml``. rosbags refuses both whole
("File end magic is invalid", "database disk image is malformed") although most of the data is
there. :func:`open_rosbag2` opens a bag with rosbags and, only when that fails on a damaged
storage file, falls back to :class:`RecoveredBag`, which reads

* **mcap**: the records one after another from the start, up to the last complete one (a
  chunk counts only when all of it is there and its CRC matches); the index that a finished
  file keeps at its end is not needed;
* **sqlite3**: a private copy whose header page count is set to the pages really present, so
  SQLite reads every row stored before the cut and reports the first missing page as an error
  where the readable part ends.

It says so once: ``recovered 1203 of ~2400 messages from BAG (its end is damaged: ...)``
(the total comes from ``metadata.yaml`` when the recorder wrote one). ``depth-fusion convert
--repair BAG OUT`` writes what was recovered into a clean bag.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

STORAGE_SUFFIXES = ('.mcap', '.db3')
MCAP_MAGIC = b'\x89MCAP0\r\n'
#: mcap opcodes that end the data section.
MCAP_FOOTER, MCAP_DATA_END = 0x02, 0x0F


#: Bags already warned about in this process.
_WARNED: set[str] = set()


class RecoveryError(ValueError):
    """Nothing of the bag could be read."""


def storage_file(path: Path) -> Path | None:
    """The one storage file of a bag folder (or the file itself), or ``None``."""
    if path.is_file():
        return path if path.suffix in STORAGE_SUFFIXES else None
    files = sorted(p for p in path.iterdir() if p.suffix in STORAGE_SUFFIXES) if path.is_dir() else []
    return files[0] if len(files) == 1 else None


def readable_rosbag2(path: str | Path) -> bool:
    """Whether ``path`` is a rosbag2 folder: its ``metadata.yaml``, or the one ``.mcap`` / ``.db3``
    of a recording cut short before it wrote one (read by :func:`open_rosbag2`'s recovery).
    (``bag_writer.is_rosbag2`` asks for a complete bag: the metadata alone.)"""
    path = Path(path)
    return path.is_dir() and ((path / 'metadata.yaml').is_file() or storage_file(path) is not None)


def expected_count(path: Path) -> int | None:
    """Message count that ``metadata.yaml`` promises (what the recorder wrote, if it got that far)."""
    meta = (path if path.is_dir() else path.parent) / 'metadata.yaml'
    try:
        import yaml

        info = yaml.safe_load(meta.read_text())['rosbag2_bagfile_information']
        return int(info['message_count'])
    except (OSError, KeyError, TypeError, ValueError):
        return None


# --- mcap -----------------------------------------------------------------------------------------


def mcap_readable_end(f: Any, start: int, size: int) -> int:
    """Offset after the last complete record from ``start`` (stops at the footer/data end)."""
    from rosbags.rosbag2.storage_mcap import decompress

    pos = start
    while pos + 9 <= size:
        f.seek(pos)
        head = f.read(9)
        op, length = head[0], struct.unpack('<Q', head[1:9])[0]
        if op in (MCAP_FOOTER, MCAP_DATA_END) or pos + 9 + length > size:
            break
        if op == 0x06:  # a chunk: complete only when its compressed records decode with their CRC
            body = f.read(length)
            try:
                _, _, usize, crc = struct.unpack('<QQQI', body[:28])
                (clen,) = struct.unpack('<I', body[28:32])
                compression = body[32 : 32 + clen].decode()
                (dlen,) = struct.unpack('<Q', body[32 + clen : 40 + clen])
                decompress(body[40 + clen : 40 + clen + dlen], compression, usize, crc)
            except Exception as exc:  # any decode / CRC / codec error: the readable part ends here
                logger.debug('mcap: damaged chunk at byte %d ends the readable part: %r', pos, exc)
                break
        pos += 9 + length
    return pos


def _truncated_mcap_reader(path: Path) -> Any:
    """A rosbags ``McapReader`` over the readable records of a damaged file."""
    from rosbags.rosbag2.errors import ReaderError
    from rosbags.rosbag2.storage_mcap import MAXSIZE, McapReader, read_sized, read_string

    class TruncatedMcapReader(McapReader):
        def _open(self) -> None:
            bio = self.bio
            if bio.read(8) != MCAP_MAGIC or bio.read(1) != b'\x01':
                raise ReaderError('not an mcap file (bad magic or header)')
            read_string(__import__('io').BytesIO(read_sized(bio)))
            self.data_start = bio.tell()
            self.data_end = mcap_readable_end(bio, self.data_start, os.fstat(bio.fileno()).st_size)
            self.meta_scan()
            stats = self.statistics
            self.connections = [
                x._replace(msgcount=stats.channel_message_counts.get(x.id, 0)) for x in self.connections
            ]
            count = stats.message_count
            self.metadata = self.metadata._replace(
                duration=stats.end_time - stats.start_time + 1 if count else 0,
                start_time=stats.start_time if count else MAXSIZE,
                end_time=stats.end_time + 1 if count else 0,
                message_count=count,
            )

        def messages(self, connections: Any, start: int | None = None, stop: int | None = None) -> Any:
            # File order (what the recorder wrote); the index that would sort it is lost.
            return self.messages_scan(connections, start, stop)

    reader = TruncatedMcapReader(path)
    reader.open()
    return reader


# --- sqlite3 --------------------------------------------------------------------------------------


class _Sqlite3Recovery:
    """The readable rows of a cut sqlite3 bag, from a private copy with a consistent header."""

    def __init__(self, path: Path) -> None:
        from rosbags.interfaces import (
            Connection,
            ConnectionExtRosbag2,
            MessageDefinition,
            MessageDefinitionFormat,
        )

        self._tmp = Path(tempfile.mkdtemp(prefix='depth_fusion_recovery_'))
        copy = self._tmp / path.name
        shutil.copyfile(path, copy)
        with open(copy, 'r+b') as f:
            header = f.read(100)
            if len(header) < 100 or not header.startswith(b'SQLite format 3\x00'):
                raise RecoveryError(f'{path}: not an sqlite3 file')
            (page,) = struct.unpack('>H', header[16:18])
            page = 65536 if page == 1 else page
            pages = os.fstat(f.fileno()).st_size // page
            f.truncate(pages * page)
            f.seek(28)
            f.write(struct.pack('>I', pages))
        self._db = sqlite3.connect(f'file:{copy}?mode=ro', uri=True, check_same_thread=False)
        try:
            topics = self._db.execute('SELECT id, name, type, serialization_format FROM topics').fetchall()
        except sqlite3.DatabaseError as exc:
            raise RecoveryError(f'{path}: its topic table is unreadable ({exc})') from None
        rows: list[tuple[int, int, int]] = []
        with contextlib.suppress(sqlite3.DatabaseError):  # the cut: every row before it is kept
            rows.extend(self._db.execute('SELECT id, topic_id, timestamp FROM messages'))
        # A row whose data (overflow pages) lay past the cut is not whole: checked once here, so
        # the count in the warning is what really plays (recovery is rare; the copy is local).
        rows = [r for r in rows if self._readable(r[0])]
        rows.sort(key=lambda r: (r[2], r[0]))
        self.rows = rows
        counts: dict[int, int] = {}
        for _, tid, _ in rows:
            counts[tid] = counts.get(tid, 0) + 1
        none = MessageDefinition(MessageDefinitionFormat.NONE, '')
        self.connections = [
            Connection(tid, name, msgtype, none, '', counts.get(tid, 0), ConnectionExtRosbag2(fmt, []), self)
            for tid, name, msgtype, fmt in topics
        ]
        stamps = [r[2] for r in rows]
        self.message_count = len(rows)
        self.start_time = min(stamps) if stamps else 2**63 - 1
        self.end_time = max(stamps) + 1 if stamps else 0

    def _readable(self, rowid: int) -> bool:
        try:
            self._db.execute('SELECT data FROM messages WHERE id = ?', (rowid,)).fetchone()
        except sqlite3.DatabaseError:
            return False
        return True

    def messages(
        self, connections: Iterable[Any], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[Any, int, bytes]]:
        by_id = {c.id: c for c in connections}
        for rowid, tid, stamp in self.rows:
            if (
                tid not in by_id
                or (start is not None and stamp < start)
                or (stop is not None and stamp >= stop)
            ):
                continue
            try:
                (data,) = self._db.execute('SELECT data FROM messages WHERE id = ?', (rowid,)).fetchone()
            except sqlite3.DatabaseError:  # its data lay beyond the cut
                continue
            yield by_id[tid], stamp, data

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._db.close()
        shutil.rmtree(self._tmp, ignore_errors=True)


# --- the reader -----------------------------------------------------------------------------------


class RecoveredBag:
    """What rosbags' ``Reader`` offers (connections, topics, messages, times), for a damaged bag."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        found = storage_file(self.path)
        if found is None:
            raise RecoveryError(f'{path}: no single .mcap or .db3 storage file to recover')
        self.storage_path = found
        if found.suffix == '.mcap':
            self._storage = _truncated_mcap_reader(found)
            meta = self._storage.metadata
            self.message_count, self.start_time, self.end_time = (
                meta.message_count,
                meta.start_time,
                meta.end_time,
            )
        else:
            self._storage = _Sqlite3Recovery(found)
            self.message_count = self._storage.message_count
            self.start_time, self.end_time = self._storage.start_time, self._storage.end_time
        self.connections = list(self._storage.connections)
        self.expected = expected_count(self.path)

    @property
    def duration(self) -> int:
        return max(self.end_time - self.start_time, 0)

    @property
    def topics(self) -> dict[str, Any]:
        from rosbags.rosbag2.reader import TopicInfo

        out: dict[str, Any] = {}
        for c in self.connections:
            if c.topic in out:
                info = out[c.topic]
                out[c.topic] = TopicInfo(
                    info.msgtype, info.msgdef, info.msgcount + c.msgcount, [*info.connections, c]
                )
            else:
                out[c.topic] = TopicInfo(c.msgtype, c.msgdef, c.msgcount, [c])
        return out

    def messages(
        self, connections: Iterable[Any] = (), start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[Any, int, bytes]]:
        return self._storage.messages(list(connections) or self.connections, start, stop)

    def summary(self) -> str:
        total = f'~{self.expected}' if self.expected else 'an unknown number of'
        return f'recovered {self.message_count} of {total} messages from {self.path}'

    def open(self) -> None:
        """Already open (the constructor reads the readable part)."""

    def close(self) -> None:
        self._storage.close()

    def __enter__(self) -> RecoveredBag:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_rosbag2(path: str | Path) -> Any:
    """An open reader of the bag at ``path``: rosbags' ``Reader`` when the bag is whole, else a
    :class:`RecoveredBag` of its readable part with one warning. Raises what rosbags raised
    when nothing can be recovered."""
    from rosbags.rosbag2 import Reader, ReaderError

    path = Path(path)
    try:
        if path.is_dir() and not (path / 'metadata.yaml').is_file():
            raise ReaderError(f'{path} has no metadata.yaml')
        reader = Reader(path)
        reader.open()
        return reader
    except (ReaderError, KeyError, sqlite3.DatabaseError) as exc:
        if storage_file(path) is None:
            raise
        try:
            bag = RecoveredBag(path)
        except Exception as rec_exc:
            logger.debug('recovery of %s failed: %r', path, rec_exc)
            raise exc from None
        if bag.message_count == 0:
            bag.close()
            raise exc from None
        if str(path) in _WARNED:  # one warning per bag, however often it is opened
            return bag
        _WARNED.add(str(path))
        logger.warning(
            '%s (its end is damaged: %s; a recorder that crashed?); '
            '`depth-fusion convert --repair %s OUT` writes a clean copy',
            bag.summary(),
            exc,
            path,
        )
        return bag


def repair_bag(
    src: str | Path, out: str | Path, storage: str = 'mcap', overwrite: bool = False
) -> tuple[int, str]:
    """Copy every readable message of ``src`` (whole or damaged) into a clean bag ``out``.

    Returns ``(messages written, what was recovered)``. The bytes are copied as they are; the
    output appears only when complete (``AtomicBagWriter``).
    """
    from rosbags.rosbag2 import ReaderError

    from .rosbag_convert import AtomicBagWriter

    try:
        reader = open_rosbag2(src)
    except (ReaderError, KeyError, sqlite3.DatabaseError) as exc:
        raise RecoveryError(f'{src}: nothing readable to repair ({exc})') from None
    written = 0
    try:
        summary = reader.summary() if isinstance(reader, RecoveredBag) else f'{src} is whole'
        with AtomicBagWriter(out, storage=storage, overwrite=overwrite) as writer:
            for conn, stamp, raw in reader.messages(reader.connections):
                writer.write_raw(conn.topic, conn.msgtype, stamp, raw)
                written += 1
    finally:
        reader.close()
    if written == 0:
        raise RecoveryError(f'{src}: no readable message')
    return written, summary
