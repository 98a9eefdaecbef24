"""The keyframes a map was integrated from, kept so the map can be rebuilt at corrected poses.

A TSDF cannot move what it holds: after a loop closure, the surface integrated at the old
poses stays where it was. What can be done (as BundleFusion de-integrates and re-integrates)
is to integrate the keyframes again at their corrected poses into a fresh map. So every
keyframe the map takes is kept here as it went in (the depth after the consistency test,
its confidence and colour), with its stamp and pose, and :meth:`KeyframeStore.correct` moves
the poses a corrected trajectory implies (:mod:`..pose_corrections`); :func:`rebuild` then
integrates them into a new engine.

Bounded in memory, whatever the image size: a keyframe is kept at half resolution (every
second pixel and row: at 320x240 a pixel of the stored depth spans 4 cm at 5 m, a voxel's
edge) as float16 depth, 8-bit confidence and 8-bit colour, 115 KB at 320x240. When the
keyframes held would take more than ``max_bytes``, every second keyframe of the older half is
dropped (consecutive keyframes overlap almost entirely, so the map loses little): the store
spans the whole run at a density that halves with age.

Each kept keyframe's images live in one private anonymous mapping of their own
(:func:`own_pages`), not on the heap: the store holds exactly the pages it counts, and a
dropped keyframe's go back to the OS at once (no ``malloc_trim`` needed). Measured with
``scripts/diag/map_memory.py`` (map_node fed 8 keyframes a second over DDS): with the images on
the heap, glibc's bytes in use grew with the store (115 -> 228 MB in 160 s) and its free,
fragmented memory by another 48 MB; with their own mappings the heap's bytes in use stay flat
(~102 MB). The heap's fragmentation around the node's other short-lived buffers is not from
the store and remains (docs/mapping.md, "Looped replays").
"""

from __future__ import annotations

import dataclasses
import mmap
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ..camera import PinholeCamera
from ..pose_corrections import CorrectionLimits, Posing, corrected_segments


@dataclass
class StoredKeyframe:
    """One keyframe as the map took it, at half resolution."""

    seq: int  # order of arrival (never reused)
    stamp: float  # s
    segment: int  # pose-jump / stream-restart segment (a world of its own)
    T_wc: np.ndarray
    camera: PinholeCamera  # of the stored (half-resolution) images
    depth: np.ndarray  # float16, NaN where not integrated
    confidence: np.ndarray | None  # uint8, confidence x 255
    rgb: np.ndarray | None  # uint8 (H, W, 3)
    #: How its pose was read from the pose source (None: as the store's caller assumes by default)
    posing: Posing | None = None

    @property
    def nbytes(self) -> int:
        """Memory held: the pages of the images' mapping (:func:`own_pages`)."""
        return mapped_bytes(sum(a.nbytes for a in (self.depth, self.confidence, self.rgb) if a is not None))

    def images(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Depth (float32), confidence (float32 in [0, 1]) and colour, as an engine takes them."""
        confidence = None if self.confidence is None else self.confidence.astype(np.float32) / 255.0
        return self.depth.astype(np.float32), confidence, self.rgb


#: Kept keyframes that get mappings of their own at most: each is one of the process's memory
#: mappings (Linux allows 65 530 by default, ``vm.max_map_count``), which torch, DDS and the
#: threads need too. A store of tiny keyframes with a large ``reintegration_max_mb`` keeps the
#: rest on the heap.
MAX_MAPPED_ENTRIES = 16384


def mapped_bytes(nbytes: int) -> int:
    """``nbytes`` rounded up to whole pages: what :func:`own_pages` maps for them."""
    return -(-int(nbytes) // mmap.PAGESIZE) * mmap.PAGESIZE


def own_pages(*arrays: np.ndarray | None, mapped: bool = True) -> list[np.ndarray | None]:
    """Copies of ``arrays`` (None stays None) in ONE private anonymous mapping of their own,
    unmapped when the last of them is released; on the heap, as any array, with ``mapped``
    False or when the system refuses a mapping (``vm.max_map_count``)."""
    sizes = [0 if a is None else int(a.nbytes) for a in arrays]
    total = sum(sizes)
    try:
        pages = mmap.mmap(-1, mapped_bytes(total), flags=mmap.MAP_PRIVATE) if total and mapped else None
    except OSError:
        pages = None
    if pages is None:
        return [None if a is None else np.array(a, order='C') for a in arrays]
    buffer = np.frombuffer(pages, dtype=np.uint8)
    out: list[np.ndarray | None] = []
    start = 0
    for a, size in zip(arrays, sizes, strict=True):
        if a is None:
            out.append(None)
            continue
        view = buffer[start : start + size].view(a.dtype).reshape(a.shape)
        view[...] = a
        out.append(view)
        start += size
    return out


def half_camera(camera: PinholeCamera) -> PinholeCamera:
    """The camera of every second pixel and row: pixel ``i`` of the half image is pixel ``2i``."""
    c = camera
    return PinholeCamera((c.width + 1) // 2, (c.height + 1) // 2, c.fx / 2, c.fy / 2, c.cx / 2, c.cy / 2)


@dataclass(frozen=True)
class CorrectionSummary:
    """What one corrected trajectory did to the store."""

    corrected: int  # keyframes the path covered
    moved: int  # of those, moved by at least the threshold
    largest_m: float
    largest_deg: float
    #: The poses of the ``others`` :meth:`KeyframeStore.correct` was given, corrected where covered.
    others: np.ndarray | None = None


@dataclass(frozen=True)
class PendingKeyframe:
    """A keyframe not (yet) in the store that a correction moves too (map_node's consistency
    window, its pose-jump test's last pose): it takes part in the interpolation of the old
    poses, so the store's newest keyframes are corrected as far as the newest pose known."""

    stamp: float
    T_wc: np.ndarray
    segment: int
    posing: Posing | None = None


@dataclass
class KeyframeStore:
    """Bounded store of the integrated keyframes (``max_bytes``, thinned with age; 0: keeps none)."""

    max_bytes: int
    entries: list[StoredKeyframe] = field(default_factory=list)
    #: Keyframes dropped to stay within ``max_bytes`` (in the map, but a rebuild leaves them out).
    thinned: int = 0
    segment: int = 0
    _next_seq: int = 0
    _bytes: int = 0

    def add(
        self,
        stamp: float,
        depth: np.ndarray,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
        segment: int | None = None,
        posing: Posing | None = None,
    ) -> StoredKeyframe | None:
        """Keep one integrated keyframe (full-resolution images, as the engine took them).

        ``posing``: how its pose was read from the pose source (:meth:`correct` undoes it to
        compare the pose with a corrected trajectory); None: the caller's default then.

        ``segment``: the one it belongs to, when the caller decided it earlier (map_node does
        so as a keyframe enters the consistency test's window, since it is integrated later);
        ``None``: the current one, or a new one when its stamp goes back (a restarted stream)."""
        if self.max_bytes <= 0:
            return None
        if segment is None:
            last = self.entries[-1] if self.entries else None
            if last is not None and stamp <= last.stamp and last.segment == self.segment:
                self.new_segment()  # the stream restarted (stamps went back): a world of its own
            segment = self.segment
        d = np.asarray(depth, np.float32)[::2, ::2]
        conf = None
        if confidence is not None:
            c = np.nan_to_num(np.asarray(confidence, np.float32)[::2, ::2], nan=0.0)
            conf = np.clip(np.rint(c * 255.0), 0, 255).astype(np.uint8)
        colour = None if rgb is None else np.asarray(rgb, np.uint8)[::2, ::2]
        entry = StoredKeyframe(
            self._next_seq,
            float(stamp),
            segment,
            np.asarray(T_wc, np.float64).copy(),
            half_camera(camera),
            *own_pages(d.astype(np.float16), conf, colour, mapped=self._map_next),
            posing,
        )
        self._next_seq += 1
        self.entries.append(entry)
        self._bytes += entry.nbytes
        while self._bytes > self.max_bytes and len(self.entries) > 1:
            self._thin()
        return entry

    def new_segment(self) -> int:
        """The poses that follow are in another world (a pose jump): never interpolated across."""
        self.segment += 1
        return self.segment

    def _thin(self) -> None:
        """Drop every second keyframe of the older half (the newest half stays dense; the first
        keyframe stays while it has company)."""
        half = max(1, len(self.entries) // 2)
        older = self.entries[:half]
        kept = older[::2] if len(older) > 1 else []
        self.thinned += len(older) - len(kept)
        self.entries = kept + self.entries[half:]
        self._bytes = sum(e.nbytes for e in self.entries)

    @property
    def _map_next(self) -> bool:
        """Whether the next keyframe gets a mapping of its own (:data:`MAX_MAPPED_ENTRIES`)."""
        return len(self.entries) < MAX_MAPPED_ENTRIES

    @property
    def memory_bytes(self) -> int:
        return self._bytes

    def clear(self) -> None:
        self.entries.clear()
        self._bytes = 0

    # --- on disk, with the map (mapping/map_file.py) --------------------------------------------------

    def to_state(self) -> dict:
        """The kept keyframes as tensors and numbers (what ``torch.load(weights_only=True)`` reads
        back), so a map file carries what a rebuild at corrected poses needs after a restart."""

        def tensor(a: np.ndarray | None) -> torch.Tensor | None:
            return None if a is None else torch.from_numpy(np.ascontiguousarray(a))

        return {
            'thinned': int(self.thinned),
            'keyframes': [
                {
                    'stamp': float(e.stamp),
                    'segment': int(e.segment),
                    'T_wc': torch.from_numpy(np.asarray(e.T_wc, np.float64).copy()),
                    'camera': [
                        float(v) for v in dataclasses.astuple(e.camera)
                    ],  # width, height, fx, fy, cx, cy
                    'depth': tensor(e.depth),
                    'confidence': tensor(e.confidence),
                    'rgb': tensor(e.rgb),
                    **_posing_state(e.posing),
                }
                for e in self.entries
            ],
        }

    def restore(self, state: dict) -> int:
        """Append the keyframes of :meth:`to_state` (a map loaded from its file) and start a new
        segment for what follows: the restarted stream is another world until a corrected
        trajectory says otherwise. Thinned to ``max_bytes`` as usual; returns how many came."""
        if self.max_bytes <= 0:
            return 0
        first_segment = self.segment + 1
        for k in state.get('keyframes', []):
            width, height, fx, fy, cx, cy = k['camera']
            entry = StoredKeyframe(
                self._next_seq,
                float(k['stamp']),
                first_segment + int(k['segment']),
                k['T_wc'].numpy().astype(np.float64),
                PinholeCamera(int(width), int(height), fx, fy, cx, cy),
                *own_pages(
                    k['depth'].numpy().astype(np.float16, copy=False),
                    None if k['confidence'] is None else k['confidence'].numpy().astype(np.uint8, copy=False),
                    None if k['rgb'] is None else k['rgb'].numpy().astype(np.uint8, copy=False),
                    mapped=self._map_next,
                ),
                _posing_from_state(k),
            )
            self._next_seq += 1
            self.entries.append(entry)
            self._bytes += entry.nbytes
            self.segment = max(self.segment, entry.segment)
        self.thinned += int(state.get('thinned', 0))
        while self._bytes > self.max_bytes and len(self.entries) > 1:
            self._thin()
        self.new_segment()
        return len(state.get('keyframes', []))

    @staticmethod
    def keyframe_bytes(camera: PinholeCamera, colour: bool = True) -> int:
        """What one kept keyframe of ``camera`` (full-resolution camera) takes."""
        half = half_camera(camera)
        return mapped_bytes(half.width * half.height * (2 + 1 + (3 if colour else 0)))

    def correct(
        self,
        path_stamps: np.ndarray,
        path_poses: np.ndarray,
        limits: CorrectionLimits,
        posing: Posing,
        others: Sequence[PendingKeyframe] = (),
    ) -> CorrectionSummary:
        """Move the stored poses as the corrected trajectory (the pose source's own poses) says,
        segment by segment, each keyframe through its own posing (``posing`` where it has none).

        Only a move that ``limits.counts`` counts as moved (a path that restates the poses it
        already gave moves nothing, and asks for no rebuild); ``limits.max_gap``: the longest
        gap between two kept keyframes that a path pose is compared across. ``others``: newer
        keyframes not stored yet (a stamp already stored is left out of them), corrected with
        the stored ones, returned in ``others``. Without them the path's poses after the newest
        stored keyframe had no old pose to be compared with, and the newest stored keyframes,
        between it and the last one they could be, stayed in the old world."""
        seen = {e.stamp for e in self.entries}
        extra = []
        for o in others:  # one of each stamp: the stored keyframe's, else the first given
            if float(o.stamp) not in seen:
                seen.add(float(o.stamp))
                extra.append(o)
        if not self.entries and not extra:
            return CorrectionSummary(0, 0, 0.0, 0.0)  # (no others either: each would be in extra)
        old = np.stack([e.T_wc for e in self.entries] + [np.asarray(o.T_wc, np.float64) for o in extra])
        stamps = np.array([e.stamp for e in self.entries] + [float(o.stamp) for o in extra])
        segments = np.array([e.segment for e in self.entries] + [o.segment for o in extra])
        posings = [e.posing or posing for e in self.entries] + [o.posing or posing for o in extra]
        fix = corrected_segments(
            stamps, old, segments, self.segment, path_stamps, path_poses, limits.max_gap, posings
        )
        n = len(self.entries)
        for e, T, corrected in zip(self.entries, fix.poses[:n], fix.corrected[:n], strict=True):
            if corrected:
                e.T_wc = T
        now = {float(s): T for s, T in zip(stamps, fix.poses, strict=True)}
        moved_others = np.stack([now[float(o.stamp)] for o in others]) if others else None
        metres, degrees = fix.moves(old)
        ok = fix.corrected[:n]
        if not ok.any():
            return CorrectionSummary(0, 0, 0.0, 0.0, moved_others)
        moved = ok & limits.counts(metres[:n], degrees[:n])
        return CorrectionSummary(
            int(ok.sum()),
            int(moved.sum()),
            float(metres[:n][ok].max()),
            float(degrees[:n][ok].max()),
            moved_others,
        )

    def newer_than(self, seq: int) -> list[StoredKeyframe]:
        """Keyframes that arrived after the one numbered ``seq``."""
        return [e for e in self.entries if e.seq > seq]

    @property
    def last_seq(self) -> int:
        return self.entries[-1].seq if self.entries else -1


def _posing_state(posing: Posing | None) -> dict:
    """A keyframe's posing in the map file (absent: a file from before, or the default)."""
    if posing is None:
        return {}
    return {
        'T_pose_cam': torch.from_numpy(np.asarray(posing.T_pose_cam, np.float64).copy()),
        'pose_offset': float(posing.offset),
    }


def _posing_from_state(k: dict) -> Posing | None:
    if k.get('T_pose_cam') is None:
        return None
    return Posing(k['T_pose_cam'].numpy().astype(np.float64), float(k.get('pose_offset', 0.0)))


def rebuild(engine: object, entries: Iterable[StoredKeyframe]) -> int:
    """Integrate ``entries`` at their (corrected) poses into ``engine`` (a fresh TSDF engine,
    :func:`.engine.make_engine`); returns how many."""
    n = 0
    for e in entries:
        depth, confidence, rgb = e.images()
        engine.integrate(depth, e.T_wc, e.camera, confidence=confidence, rgb=rgb)
        n += 1
    return n
