"""The TSDF map on disk, so a robot keeps its map across restarts (map_node's ``map_file``).

A mesh (``~/save_map``'s ``.ply``) is for people and other tools; it cannot be integrated
into again. This file is the map itself: the torch engine's used voxel blocks (coordinates,
TSDF, weight, colour), its voxel and block size and truncation, and the world frame it is in,
written with ``torch.save`` (tensors only, read back with ``weights_only=True``: loading a map
runs no code) to a temporary file renamed over the old one, so a crash while saving never
leaves half a map. It holds the whole map, the blocks archived on disk (mapping/block_archive.py)
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
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from .block_surface import BlockGrid
from .keyframe_store import KeyframeStore
from .torch_tsdf import TorchTSDF

FORMAT = 'depth_fusion_ros.tsdf/1'


@dataclass
class LoadedMap:
    """What a map file gave besides the blocks now in the engine."""

    world_frame: str
    #: The blocks a rebuild at corrected poses starts from (coords, tsdf, weight, colour on the
    #: CPU), or None: the kept keyframes are the whole map.
    base: BlockGrid | None
    #: Kept keyframes restored into the store.
    keyframes: int


def save_tsdf(
    engine: TorchTSDF,
    path: str | Path,
    world_frame: str,
    store: KeyframeStore | None = None,
    base: BlockGrid | None = None,
) -> int:
    """Write the map's blocks, archived ones included, to ``path`` (atomically), with the kept
    keyframes of ``store`` and the rebuild's ``base`` when given; returns how many blocks."""
    path = Path(path)
    blocks = engine.all_blocks()
    camera = engine.camera_position
    state = {
        'format': FORMAT,
        'voxel_size': float(engine.config.voxel_size),
        'block_size': int(engine.config.block_size),
        'truncation': float(engine.trunc),
        'world_frame': world_frame,
        'coords': blocks.coords.cpu(),
        'tsdf': blocks.tsdf.cpu(),
        'weight': blocks.weight.cpu(),
        'colour': blocks.colour.cpu(),
    }
    if camera is not None:
        state['camera_position'] = torch.as_tensor(camera, dtype=torch.float64)
    if store is not None:
        state['store'] = store.to_state()
        if base is not None:
            state['base'] = {k: getattr(base, k).cpu() for k in ('coords', 'tsdf', 'weight', 'colour')}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + '.tmp')
    torch.save(state, tmp)
    os.replace(tmp, path)
    return int(blocks.coords.shape[0])


def load_tsdf(engine: TorchTSDF, path: str | Path) -> str:
    """Fill the (empty) ``engine`` with the map in ``path``; returns its world frame."""
    return load_map(engine, path).world_frame


def read_state(path: str | Path) -> dict:
    """The saved map as ``torch.save`` wrote it (tensors and numbers; no code runs);
    ``ValueError`` naming the file when it is not such a map."""
    path = Path(path)
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # a truncated, foreign or corrupt file: one line, not a traceback
        raise ValueError(f'map file {path}: not readable as a map ({type(exc).__name__}: {exc})') from None
    if not isinstance(state, dict) or state.get('format') != FORMAT:
        raise ValueError(f'map file {path}: not a depth_fusion_ros TSDF map (format {FORMAT})')
    return state


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
    n = int(state['coords'].shape[0])
    if n > cfg.max_blocks and not cfg.archive:
        raise ValueError(
            f'map file {path}: {n} blocks, more than map.max_blocks={cfg.max_blocks} with map.archive off'
        )
    camera = state.get('camera_position')
    centre = None if camera is None else camera.numpy()
    engine.load_blocks(state['coords'], state['tsdf'], state['weight'], state['colour'], centre=centre)
    if centre is not None:
        engine.camera_position = centre.copy()
    world_frame = str(state.get('world_frame') or '')
    kept = state.get('store')
    if store is None or kept is None or not kept.get('keyframes') or store.max_bytes <= 0:
        return LoadedMap(world_frame, engine.all_blocks().clone(), 0)  # nothing to rebuild from: fixed
    restored = store.restore(kept)
    base = file_blocks(state, cfg.min_weight, 'base') if state.get('base') is not None else None
    return LoadedMap(world_frame, base, restored)
