"""The TSDF map on disk, so a robot keeps its map across restarts (map_node's ``map_file``).

A mesh (``~/save_map``'s ``.ply``) is for people and other tools; it cannot be integrated
into again. This file is the map itself: the torch engine's used voxel blocks (coordinates,
TSDF, weight, colour), its voxel and block size and truncation, and the world frame it is in,
written to a temporary file renamed over the old one, so a crash while saving never leaves half
a map. It holds the whole map, the blocks archived on disk (mapping/block_archive.py)
included, and where the camera last was. Loading checks that the file is such a map and that it
fits the node's configuration (same voxel and block size; more than ``max_blocks`` blocks only
with the archive on: the ones nearest the last camera position are held in memory, the rest
archived), and says in one line what does not.

With the map come the keyframes it keeps for a rebuild at corrected poses
(:class:`.keyframe_store.KeyframeStore`, half resolution, bounded) and the part of the map a
rebuild cannot move (``base``: a map loaded before those keyframes were taken), so a corrected
trajectory that arrives after a restart still moves what the earlier run mapped: the rebuild
integrates the base and the kept keyframes of both runs at their corrected poses. A file
without keyframes (an older one, or ``reintegration_max_mb`` 0) loads as a base that cannot
move, as before.

**A map larger than memory goes through the file a part at a time** (format 2). The blocks
are raw arrays at fixed offsets (coordinates int64, TSDF, weight and colour float32, the map's
then the base's), written :data:`CHUNK` blocks at a time as the engine reads them back from its
archive, and read back through a memory mapping, so neither saving nor loading holds the whole
map in memory (format 1 was one ``torch.save`` of it all: a 4 GiB archive needed 4 GiB more
to save). After them come the small things (sizes, frame, camera, kept keyframes) as one
``torch.save`` (tensors only, read back with ``weights_only=True``: loading a map runs no
code), and a trailer: that part's offset and :data:`MAGIC`. A base loaded from a file stays in
that file's mapping (on Linux a file renamed over keeps its data while it is mapped). Format 1
files still load.
"""

from __future__ import annotations

import io
import logging
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .block_surface import BlockGrid
from .config import MapConfig, min_weight_for
from .file_pages import unmap_pages
from .keyframe_store import KeyframeStore
from .torch_tsdf import TorchTSDF

log = logging.getLogger(__name__)

FORMAT = 'depth_fusion_ros.tsdf/2'
#: The whole-file ``torch.save`` of earlier releases (still read).
FORMAT_1 = 'depth_fusion_ros.tsdf/1'
#: The file's last 8 bytes (after the header's offset, 8 bytes little-endian).
MAGIC = b'DFTSDF2\n'
#: Blocks written (and read) at a time: 10 MiB at 8³ voxels.
CHUNK = 1024
#: Every array starts at a multiple of this (cache lines; any page-aligned mapping is then cheap).
ALIGN = 64
#: The arrays of a part, in file order: (name, dtype, shape of one block's row given V voxels).
ARRAYS: tuple[tuple[str, np.dtype, Callable[[int], tuple[int, ...]]], ...] = (
    ('coords', np.dtype(np.int64), lambda v: (3,)),
    ('tsdf', np.dtype(np.float32), lambda v: (v,)),
    ('weight', np.dtype(np.float32), lambda v: (v,)),
    ('colour', np.dtype(np.float32), lambda v: (3, v)),
)


@dataclass
class LoadedMap:
    """What a map file gave besides the blocks now in the engine."""

    world_frame: str
    #: The blocks a rebuild at corrected poses starts from (coords, tsdf, weight, colour on the
    #: CPU, read from the map file as needed), or None: the kept keyframes are the whole map.
    base: BlockGrid | None
    #: Kept keyframes restored into the store.
    keyframes: int


#: Blocks by row (``BlockGrid.rows``, ``TorchTSDF.whole_map``'s loader).
Loader = Callable[[torch.Tensor], BlockGrid]
#: Where a part's arrays lie: ``{array: (offset, shape)}``.
Arrays = dict[str, tuple[int, tuple[int, ...]]]


def _layout(parts: dict[str, int], voxels: int) -> tuple[dict[str, Arrays], int]:
    """Where each part's arrays lie (``{part: Arrays}``), and where they end."""
    where: dict[str, Arrays] = {}
    offset = 0
    for part, n in parts.items():
        where[part] = {}
        for name, dtype, row in ARRAYS:
            shape = (int(n), *row(voxels))
            where[part][name] = (offset, shape)
            offset += -(-int(np.prod(shape)) * dtype.itemsize // ALIGN) * ALIGN
    return where, offset


def _write_part(f: io.BufferedWriter, arrays: Arrays, n: int, load: Loader) -> None:
    """The blocks ``load(rows)`` gives, CHUNK rows at a time, into their arrays."""
    for start in range(0, n, CHUNK):
        grid = load(torch.arange(start, min(start + CHUNK, n)))
        tensors = (grid.coords, grid.tsdf, grid.weight, grid.colour)
        for (name, dtype, _), tensor in zip(ARRAYS, tensors, strict=True):
            offset = arrays[name][0]
            a = np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=dtype)
            f.seek(offset + start * (a.nbytes // max(1, a.shape[0])))
            f.write(memoryview(a).cast('B'))


def save_tsdf(
    engine: TorchTSDF,
    path: str | Path,
    world_frame: str,
    store: KeyframeStore | None = None,
    base: BlockGrid | None = None,
) -> int:
    """Write the map's blocks, archived ones included, to ``path`` (atomically), with the kept
    keyframes of ``store`` and the rebuild's ``base`` when given; returns how many blocks.
    At most :data:`CHUNK` blocks are in memory at a time beyond the map's own."""
    path = Path(path)
    coords, load = engine.whole_map()
    parts = {'': (coords, load)}
    if store is not None and base is not None:
        parts['base'] = (base.coords, base.rows)
    header: dict = {
        'format': FORMAT,
        'voxel_size': float(engine.config.voxel_size),
        'block_size': int(engine.config.block_size),
        'truncation': float(engine.trunc),
        # What the weights are: the confidence to this power (files without it: 1, before 2026-12-06).
        'confidence_power': float(engine.config.confidence_power),
        # ... over the depth to this power (files without it: 0).
        'depth_power': float(engine.config.depth_power),
        'world_frame': world_frame,
        'parts': {name: int(c.shape[0]) for name, (c, _) in parts.items()},
    }
    camera = engine.camera_position
    if camera is not None:
        header['camera_position'] = torch.as_tensor(camera, dtype=torch.float64)
    if store is not None:
        header['store'] = store.to_state()
    layout, end = _layout(header['parts'], engine.block_voxels)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + '.tmp')
    try:
        with open(tmp, 'wb') as f:
            for name, (c, rows) in parts.items():
                _write_part(f, layout[name], int(c.shape[0]), rows)
            f.seek(end)
            torch.save(header, f)
            f.write(struct.pack('<Q', end) + MAGIC)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # gone once renamed; after a failure (a full disk) no half file stays
    return int(coords.shape[0])


def load_tsdf(engine: TorchTSDF, path: str | Path) -> str:
    """Fill the (empty) ``engine`` with the map in ``path``; returns its world frame."""
    return load_map(engine, path).world_frame


def read_state(path: str | Path) -> dict:
    """The saved map as a dict: the sizes, frame, camera and kept keyframes, and the blocks as
    tensors mapped from the file (read as they are indexed; format 1: all read); ``ValueError``
    naming the file when it is not such a map."""
    path = Path(path)
    try:
        state = _read_header(path)
    except Exception as exc:  # a truncated, foreign or corrupt file: one line, not a traceback
        raise ValueError(f'map file {path}: not readable as a map ({type(exc).__name__}: {exc})') from None
    if not isinstance(state, dict) or state.get('format') not in (FORMAT, FORMAT_1):
        raise ValueError(f'map file {path}: not a depth_fusion_ros TSDF map (format {FORMAT})')
    if state['format'] == FORMAT:
        try:
            _map_blocks(path, state)
        except (ValueError, OSError, KeyError, TypeError) as exc:
            raise ValueError(f'map file {path}: its blocks do not match its header ({exc})') from None
    return state


def _read_header(path: Path) -> object:
    """Format 2: the ``torch.save`` part the trailer points at, with its offset as
    ``header_offset``; otherwise the whole file (format 1)."""
    with open(path, 'rb') as f:
        size = f.seek(0, os.SEEK_END)
        if size >= 16:
            f.seek(size - 16)
            trailer = f.read(16)
            if trailer[8:] == MAGIC:
                (offset,) = struct.unpack('<Q', trailer[:8])
                if not 0 <= offset <= size - 16:
                    raise ValueError(f'header offset {offset} outside the file ({size} bytes)')
                f.seek(offset)
                header = io.BytesIO(f.read(size - 16 - offset))
                state = torch.load(header, map_location='cpu', weights_only=True)
                if isinstance(state, dict):
                    state['header_offset'] = offset
                return state
    return torch.load(path, map_location='cpu', weights_only=True)


def _map_blocks(path: Path, state: dict) -> None:
    """Put each part's arrays into ``state`` (the map's at the top, the base's under ``base``) as
    tensors over a copy-on-write mapping of the file: nothing is read until it is indexed."""
    voxels = int(state['block_size']) ** 3
    state['mappings'] = []
    layout, end = _layout(state['parts'], voxels)
    if end > state['header_offset']:
        raise ValueError(f'the blocks would end at byte {end}, past the header at {state["header_offset"]}')
    for part, arrays in layout.items():
        target = state if not part else state.setdefault(part, {})
        for name, dtype, _ in ARRAYS:
            offset, shape = arrays[name]
            if shape[0] == 0:
                target[name] = torch.from_numpy(np.zeros(shape, dtype))
                continue
            mapped = np.memmap(path, dtype=dtype, mode='c', offset=offset, shape=shape)
            state['mappings'].append(mapped)
            target[name] = torch.from_numpy(mapped)


def unmap_file_pages(state: dict) -> None:
    """Drop the pages of a :func:`read_state` map that reading touched from the process (its
    mappings are copy-on-write and never written: the next read maps them from the file again).
    After a load, the blocks are in the engine and its archive: the file's pages would
    otherwise stay in the process's resident set, the size of the map."""
    for mapped in state.get('mappings', ()):
        unmap_pages(mapped)


def file_powers(state: dict) -> tuple[float, float]:
    """What a read map's weights are: the powers of the confidence and of the depth (1 and 0 for
    files written before ``map.confidence_power``, 0 for the depth before ``map.depth_power``)."""
    return float(state.get('confidence_power', 1.0)), float(state.get('depth_power', 0.0))


def file_min_weight(state: dict, config: MapConfig) -> float:
    """``config.min_weight`` for a read map's own weights: the threshold of the same single
    observation where the file was saved with other weights (``mesh`` and the fixed base of
    :func:`load_map` extract it with this)."""
    return min_weight_for(config, *file_powers(state))


def file_blocks(state: dict, min_weight: float, part: str = '') -> BlockGrid:
    """The blocks of a :func:`read_state` map (CPU), surface voxels needing ``min_weight``;
    ``part='base'``: the fixed base saved beside the kept keyframes instead of the map."""
    blocks = state[part] if part else state
    arrays = (blocks['coords'], blocks['tsdf'], blocks['weight'], blocks['colour'])
    return BlockGrid(*arrays, int(state['block_size']), float(state['voxel_size']), float(min_weight))


def load_map(engine: TorchTSDF, path: str | Path, store: KeyframeStore | None = None) -> LoadedMap:
    """Fill the (empty) ``engine`` with the map in ``path`` and ``store`` with its kept keyframes.

    ``ValueError`` naming the file and the reason when it is not a map this engine can take."""
    path = Path(path)
    state = read_state(path)
    cfg = engine.config
    if abs(float(state['voxel_size']) - cfg.voxel_size) > 1e-9 or int(state['block_size']) != cfg.block_size:
        raise ValueError(
            f'map file {path}: {state["voxel_size"] * 100:g} cm voxels in blocks of {state["block_size"]}, '
            f'map_node is configured for {cfg.voxel_size * 100:g} cm in blocks of {cfg.block_size} '
            "(set map.voxel_size and map.block_size to the file's)"
        )
    power = file_powers(state)
    if power != (cfg.confidence_power, cfg.depth_power):
        log.warning(
            'map file %s: its weights are the confidence to the power %g over the depth to %g, new keyframes '
            'weigh them %g and %g (map.confidence_power, map.depth_power): its voxels and new observations '
            'do not count alike until overwritten',
            path,
            *power,
            cfg.confidence_power,
            cfg.depth_power,
        )
    n = int(state['coords'].shape[0])
    if n > cfg.max_blocks and not cfg.archive:
        raise ValueError(
            f'map file {path}: {n} blocks, more than map.max_blocks={cfg.max_blocks} with map.archive off'
        )
    camera = state.get('camera_position')
    centre = None if camera is None else camera.numpy()
    engine.load_blocks(state['coords'], state['tsdf'], state['weight'], state['colour'], centre=centre)
    unmap_file_pages(state)
    if centre is not None:
        engine.camera_position = centre.copy()
    world_frame = str(state.get('world_frame') or '')
    kept = state.get('store')
    if store is None or kept is None or not kept.get('keyframes') or store.max_bytes <= 0:
        # Nothing to rebuild from: all of it is the fixed base, which stays in the file's mapping.
        return LoadedMap(world_frame, file_blocks(state, file_min_weight(state, cfg)), 0)
    restored = store.restore(kept)
    has_base = state.get('base') is not None
    base = file_blocks(state, file_min_weight(state, cfg), 'base') if has_base else None
    return LoadedMap(world_frame, base, restored)
