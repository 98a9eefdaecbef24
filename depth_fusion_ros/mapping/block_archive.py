"""Voxel blocks evicted from a bounded map, kept on disk until the camera comes back.

Why: ``map.max_blocks`` caps the map's memory, so a robot that maps a building holds only the
blocks around its camera. Without an archive the blocks it evicts are gone: the saved mesh
holds only the last room, and a room visited again is mapped from nothing. With it, an
evicted block is written to one file of fixed-size records (its TSDF, weight and colour,
float32 as in memory, so a block comes back bit for bit), and when a keyframe needs a block
the archive holds, the block is read back instead of starting empty. The saved mesh and the
map file hold the whole map, archived blocks included.

The file is a ``numpy.memmap`` of ``(slots, 5 · block_voxels)`` float32 records, grown by
doubling up to ``max_bytes`` and reused through a free list; a dict maps each block's packed
key (:mod:`.keys`) to its slot. The pages each read or write touched are unmapped from the
process after it (they stay in the page cache, written back by the kernel): otherwise the
process's resident set would grow with the archive's size, which it does not hold. Blocks past
``max_bytes``, or that the disk refuses (full, read-only), are lost and counted (``lost``),
never silently. The archive is a spill area of one map, not a storage format: it lives in a
directory of its own, made on the first eviction and deleted with the map (``close``, or at
exit). A process killed before it could delete its archive (SIGKILL, a power cut) leaves the
directory behind. Each archive holds an exclusive ``flock`` on a lock file in its directory
for its whole life (the kernel drops it when the process dies, whatever killed it, and it
holds across PID namespaces: containers sharing ``~/.ros``); the next archive made in the same
parent deletes the directories whose lock it can take. A map that must outlive the process is
the map file (:mod:`.map_file`).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import weakref
from pathlib import Path

import numpy as np
import torch

from .file_pages import unmap_pages
from .keys import pack, unpack

log = logging.getLogger(__name__)

#: Slots of the first file (10 KiB each at 8³ voxels): doubled as needed up to the cap.
INITIAL_SLOTS = 256

#: Prefix of an archive's directory; the owning process id follows it.
PREFIX = 'depth_fusion_map_archive_'


#: The lock file an archive holds (``flock``) while its process lives.
LOCK_NAME = 'owner.lock'


def remove_stale(parent: Path) -> int:
    """Delete the archive directories in ``parent`` whose owner is gone (a process killed before
    it could delete its own: its lock is free); returns how many. POSIX only (``fcntl``)."""
    try:
        import fcntl
    except ImportError:
        return 0
    removed = 0
    for folder in parent.glob(f'{PREFIX}*'):
        lock = folder / LOCK_NAME
        if not folder.is_dir() or not lock.exists():  # not an archive, or one being made this moment
            continue
        try:
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # held: its process runs
            continue
        finally:
            os.close(fd)
        shutil.rmtree(folder, ignore_errors=True)
        removed += 1
    if removed:
        log.info('map archive: removed %d archives left by stopped processes in %s', removed, parent)
    return removed


def _take_lock(folder: Path) -> int | None:
    """Hold ``folder``'s lock file for the archive's life: the descriptor (None without fcntl)."""
    try:
        import fcntl
    except ImportError:
        return None
    fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


def _reserve(path: Path, size: int) -> None:
    """Grow the file to ``size`` bytes with its disk space allocated now: a memory-mapped write
    into a sparse file on a full disk is a SIGBUS that kills the process, while a failed
    allocation here is an ``OSError`` the archive counts (its blocks lost) and survives."""
    with open(path, 'r+b') as f:
        if hasattr(os, 'posix_fallocate'):
            os.posix_fallocate(f.fileno(), 0, size)
        else:  # no such call here: a sparse file, as before
            f.truncate(size)


def _remove(folder: Path, lock_fd: int | None) -> None:
    shutil.rmtree(folder, ignore_errors=True)
    if lock_fd is not None:
        os.close(lock_fd)


class BlockArchive:
    """Evicted blocks on disk: ``put`` when evicted, ``take`` when needed again, ``coords`` and
    ``read`` for the whole map a part at a time."""

    def __init__(self, block_voxels: int, directory: str | Path = '', max_bytes: float = 4 * 2**30) -> None:
        self.block_voxels = int(block_voxels)
        #: floats per record: tsdf, weight and three colour planes.
        self.record = 5 * self.block_voxels
        self.max_slots = max(0, int(max_bytes // (4 * self.record)))
        self.directory = str(directory)
        #: Blocks that could not be archived (cap reached, disk error): gone for good.
        self.lost = 0
        #: Blocks read back into the map so far.
        self.restored = 0
        self._slots: dict[int, int] = {}
        #: The ``put`` each archived block was last written by (a block written again, after it
        #: came back and changed, has a new one: :meth:`versions`).
        self._written: dict[int, int] = {}
        self._puts = 0
        self._free: list[int] = []
        self._capacity = 0
        self._path: Path | None = None
        self._memmap: np.memmap | None = None
        self._finalizer: weakref.finalize | None = None
        self._warned: set[str] = set()

    # --- state ----------------------------------------------------------------------------------------

    @property
    def n_blocks(self) -> int:
        """Blocks held on disk now."""
        return len(self._slots)

    @property
    def disk_bytes(self) -> int:
        """Bytes of the archive file (its capacity, not only the used slots)."""
        return self._capacity * self.record * 4

    @property
    def path(self) -> Path | None:
        """The archive file, once something was archived."""
        return self._path

    # --- put / take -----------------------------------------------------------------------------------

    def put(
        self, coords: torch.Tensor, tsdf: torch.Tensor, weight: torch.Tensor, colour: torch.Tensor
    ) -> int:
        """Archive ``(N, 3)`` block coordinates with their voxels; returns how many were kept
        (the rest, past the cap or refused by the disk, are counted in ``lost``)."""
        n = int(coords.shape[0])
        if n == 0:
            return 0
        keys = pack(coords.cpu()).tolist()
        room = len(self._free) + self.max_slots - self._capacity
        keep = min(n, room + sum(k in self._slots for k in keys))
        if keep < n:
            self._lose(n - keep, f'the archive is full ({self.max_slots} blocks, map.archive_max_mb)')
        if keep == 0:
            return 0
        rows = torch.cat(
            (tsdf[:keep].reshape(keep, -1), weight[:keep].reshape(keep, -1), colour[:keep].reshape(keep, -1)),
            dim=1,
        )
        try:
            slots = self._slots_for(keys[:keep])
            self._memmap[slots] = rows.to('cpu', torch.float32).numpy()
            unmap_pages(self._memmap)
        except OSError as exc:  # disk full, directory gone, read-only: the blocks are lost, said once
            for key in keys[:keep]:
                slot = self._slots.pop(key, None)
                self._written.pop(key, None)
                if slot is not None:
                    self._free.append(slot)
            self._lose(keep, f'writing {self._path or self.directory or "the archive"} failed: {exc}')
            return 0
        self._puts += 1
        self._written.update(dict.fromkeys(keys[:keep], self._puts))
        return keep

    def take(self, coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The archived blocks among ``(N, 3)`` coordinates, removed from the archive:
        ``(found, tsdf, weight, colour)``, ``found`` a bool mask over ``coords`` and the voxels
        of the found blocks in its order (CPU float32)."""
        found = torch.zeros(int(coords.shape[0]), dtype=torch.bool)
        slots: list[int] = []
        if not self._slots:
            return (found, *self._rows(slots))
        hits = []
        for i, key in enumerate(pack(coords.cpu()).tolist()):
            slot = self._slots.pop(key, None)
            if slot is not None:
                hits.append(i)
                slots.append(slot)
                del self._written[key]
        found[hits] = True
        self._free.extend(slots)
        self.restored += len(slots)
        return (found, *self._rows(slots))

    def coords(self) -> torch.Tensor:
        """(N, 3) block coordinates of the archived blocks (no voxels read)."""
        return unpack(torch.tensor(list(self._slots.keys()), dtype=torch.int64)).reshape(-1, 3)

    def versions(self) -> dict[int, int]:
        """Packed key -> the write that put each archived block there (a copy): what changed
        since an earlier look (``mapping/archived_surface.py``)."""
        return dict(self._written)

    def read(self, coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The voxels of archived blocks ``coords`` (all archived; left in the archive):
        ``(tsdf, weight, colour)`` on the CPU, in their order."""
        return self._rows([self._slots[k] for k in pack(coords.cpu()).tolist()])

    def close(self) -> None:
        """Delete the archive file and its directory (the map is going)."""
        self._memmap = None
        self._slots.clear()
        self._written.clear()
        self._free.clear()
        self._capacity = 0
        if self._finalizer is not None:
            self._finalizer()
            self._finalizer = None
        self._path = None

    # --- storage --------------------------------------------------------------------------------------

    def _rows(self, slots: list[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The records of ``slots`` split into ``(tsdf, weight, colour)`` (CPU float32 copies)."""
        v = self.block_voxels
        rows = torch.from_numpy(np.array(self._memmap[slots])) if slots else torch.zeros((0, self.record))
        if slots:
            unmap_pages(self._memmap)
        return rows[:, :v], rows[:, v : 2 * v], rows[:, 2 * v :].reshape(-1, 3, v)

    def _lose(self, count: int, why: str) -> None:
        """Count lost blocks; warn once per kind of cause (the node counts and throttles the rest)."""
        self.lost += count
        kind = why.split(' ', 1)[0]
        level = logging.DEBUG if kind in self._warned else logging.WARNING
        self._warned.add(kind)
        log.log(level, 'map archive: %d evicted blocks lost: %s', count, why)

    def _slots_for(self, keys: list[int]) -> list[int]:
        """A slot per key (its own if archived already, else a free one, growing the file)."""
        new = [k for k in keys if k not in self._slots]
        short = len(new) - len(self._free)
        if short > 0:
            self._grow(self._capacity + short)
        for key in new:
            self._slots[key] = self._free.pop()
        return [self._slots[k] for k in keys]

    def _grow(self, needed: int) -> None:
        capacity = min(self.max_slots, max(needed, 2 * self._capacity, INITIAL_SLOTS))
        if self._path is None:
            parent = Path(self.directory or tempfile.gettempdir())
            parent.mkdir(parents=True, exist_ok=True)
            remove_stale(parent)
            folder = Path(tempfile.mkdtemp(prefix=f'{PREFIX}{os.getpid()}_', dir=parent))
            self._finalizer = weakref.finalize(self, _remove, folder, _take_lock(folder))
            self._path = folder / 'blocks.f32'
            self._path.touch()
            log.info('map archive: evicted blocks go to %s', self._path)
        _reserve(self._path, capacity * self.record * 4)
        self._memmap = np.memmap(self._path, dtype=np.float32, mode='r+', shape=(capacity, self.record))
        self._free.extend(range(capacity - 1, self._capacity - 1, -1))  # lowest slot popped first
        self._capacity = capacity
