"""``MapConfig``: what bounds and weights the TSDF map (shared by every engine).

A TSDF integrates depth along camera rays into a signed distance that is truncated at
``truncation`` metres around the surface. The map is *bounded*: depth outside
``[min_depth, max_depth]`` is ignored and at most ``max_blocks`` voxel blocks of
``block_size``³ voxels are held in memory (blocks farthest from the camera are evicted when a
new keyframe needs room), so memory is capped whatever the replay length. Evicted blocks go to
a disk archive (``archive``, mapping/block_archive.py) and come back when the camera does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Engines: ``auto`` picks Open3D when it is installed and torch otherwise.
ENGINES = ('auto', 'torch', 'open3d')


#: The depth (m) at which ``map.min_weight``'s default keeps the single observation it kept
#: before the depth term (0.002 of squared confidence, 2026-12-06). A map file saved with other
#: weights is extracted at the threshold of that same observation.
REFERENCE_DEPTH_M = 2.5
#: ``map.min_weight`` before the depth term: one observation of confidence 0.045.
_SQUARED_CONFIDENCE_MIN_WEIGHT = 0.002


@dataclass
class MapConfig:
    """TSDF map parameters (voxel size, truncation, depth range, memory cap, weighting)."""

    #: Edge of one voxel (m).
    voxel_size: float = 0.04
    #: TSDF truncation distance (m); 0 = 3 voxels.
    truncation: float = 0.0
    #: Depth outside [min_depth, max_depth] (m) is not integrated.
    min_depth: float = 0.1
    max_depth: float = 6.0
    #: Most voxel blocks held at once (the memory cap); the farthest from the camera are evicted.
    max_blocks: int = 10000
    #: Voxels along each edge of a block.
    block_size: int = 8
    #: Pixels whose confidence is below this are left out; the rest are weighted by confidence.
    #: 0: the consistency test below decides which pixels enter, the confidence only weights them.
    min_confidence: float = 0.0
    #: A pixel's integration weight is its confidence to this power (torch engine; Open3D weighs
    #: every pixel 1). The fused confidence falls off slowly with the depth's error (docs/fusion.md:
    #: a pixel 10x less confident is about 3x less accurate), so a voxel seen by a few confident
    #: pixels and many doubtful ones took the doubtful ones' depth; squared, the confident ones
    #: decide where they exist (docs/mapping.md, "Weights that follow the error").
    confidence_power: float = 2.0
    #: ... divided by its depth (m) to this power (torch engine). The fused confidence ranks a
    #: pixel's error relative to its depth, while a voxel averages distances in metres: a pixel twice
    #: as far off in metres counts a quarter, as in voxblox's 1 / z^2 (docs/mapping.md, "Weights in
    #: metres"). 0: the confidence alone.
    depth_power: float = 2.0
    #: Keyframes before and after each keyframe that its depth is checked against
    #: (mapping/consistency.py); the map lags this many keyframes. 0: no check.
    consistency_span: int = 2
    #: A pixel agrees with another keyframe when the depth there is within this fraction of its own.
    consistency_tolerance: float = 0.05
    #: Other keyframes that must agree before a pixel is integrated.
    consistency_views: int = 1
    #: A voxel's weight stops growing here, so a changed scene can still overwrite it.
    max_weight: float = 50.0
    #: Surface extraction keeps voxels observed with at least this accumulated weight (the fused
    #: confidence, times the agreement factor since 2026-11-27, to ``confidence_power``, over the
    #: depth to ``depth_power``: docs/mapping.md). One observation at :data:`REFERENCE_DEPTH_M`
    #: needs the confidence it needed before the depth term (0.002 of confidence squared; 0.05 while
    #: the weight was the confidence itself).
    min_weight: float = _SQUARED_CONFIDENCE_MIN_WEIGHT / REFERENCE_DEPTH_M**2  # 0.00032
    #: Pixel stride of the block allocation pass: 4 px are 9 cm at 6 m (320 px wide, 60° field of
    #: view), well inside one 32 cm block, so no block is missed.
    allocation_stride: int = 4
    #: ``auto``, ``torch`` or ``open3d``.
    engine: str = 'auto'
    #: Evicted blocks go to a file on disk and come back when a keyframe needs them again; the
    #: saved mesh and map file hold them (torch engine). False: evicted blocks are dropped.
    archive: bool = True
    #: Where the archive's directory is made ('': the system's temporary directory; map_node
    #: uses $ROS_HOME/depth_fusion_ros/map_archive instead).
    archive_dir: str = ''
    #: Most disk the archive takes (MiB); blocks evicted past it are lost (counted).
    archive_max_mb: float = 4096.0
    #: torch / Open3D device: ``cpu``, ``cuda``, ``cuda:1``.
    device: str = 'cpu'

    @property
    def truncation_m(self) -> float:
        return self.truncation if self.truncation > 0 else 3.0 * self.voxel_size

    @property
    def block_m(self) -> float:
        """Edge of one block (m)."""
        return self.voxel_size * self.block_size

    @property
    def bytes_per_block(self) -> int:
        """TSDF + weight (float32) + colour (3 x float32) per block: what ``max_blocks`` caps."""
        return self.block_size**3 * 4 * 5

    def validate(self) -> MapConfig:
        """``self``, or ``ValueError`` naming the bad field."""
        checks = [
            ('voxel_size', self.voxel_size > 0 and math.isfinite(self.voxel_size), 'must be > 0'),
            ('truncation', self.truncation >= 0, 'must be >= 0 (0: 3 voxels)'),
            ('min_depth', self.min_depth >= 0, 'must be >= 0'),
            ('max_depth', self.max_depth > self.min_depth, 'must be > min_depth'),
            ('max_blocks', self.max_blocks >= 1, 'must be >= 1'),
            ('block_size', 2 <= self.block_size <= 32, 'must be in [2, 32]'),
            ('min_confidence', 0 <= self.min_confidence <= 1, 'must be in [0, 1]'),
            (
                'confidence_power',
                0.01 <= self.confidence_power <= 8,
                'must be in [0.01, 8]',
            ),
            ('depth_power', 0 <= self.depth_power <= 4, 'must be in [0, 4]'),
            ('consistency_span', 0 <= self.consistency_span <= 10, 'must be in [0, 10]'),
            ('consistency_tolerance', 0 < self.consistency_tolerance < 1, 'must be in (0, 1)'),
            (
                'consistency_views',
                1 <= self.consistency_views <= 2 * max(1, self.consistency_span),
                'must be in [1, 2 x consistency_span]',
            ),
            ('max_weight', self.max_weight > 0, 'must be > 0'),
            ('min_weight', self.min_weight >= 0, 'must be >= 0'),
            ('allocation_stride', self.allocation_stride >= 1, 'must be >= 1'),
            ('engine', self.engine in ENGINES, f'must be one of {", ".join(ENGINES)}'),
            (
                'archive_max_mb',
                self.archive_max_mb >= 0 and math.isfinite(self.archive_max_mb),
                'must be >= 0',
            ),
        ]
        for name, ok, why in checks:
            if not ok:
                raise ValueError(f'map.{name}={getattr(self, name)!r}: {why}')
        return self


def min_weight_for(config: MapConfig, power: float, depth_power: float) -> float:
    """``config.min_weight`` for weights that are the confidence to ``power`` over the depth to
    ``depth_power`` (a map file saved with other weights): the threshold of the same single
    observation at :data:`REFERENCE_DEPTH_M`."""
    same = power == config.confidence_power and depth_power == config.depth_power
    if config.min_weight <= 0 or same:
        return config.min_weight
    at_reference = config.min_weight * REFERENCE_DEPTH_M**config.depth_power  # confidence to its power
    confidence = at_reference ** (1.0 / config.confidence_power)
    return float(confidence**power / REFERENCE_DEPTH_M**depth_power)


#: Descriptions of the fields, for the node's parameter table.
MAP_PARAMETER_DESCRIPTIONS = {
    'voxel_size': 'edge of one TSDF voxel (m)',
    'truncation': 'TSDF truncation distance (m); 0 = 3 voxels',
    'min_depth': 'depth nearer than this (m) is not integrated',
    'max_depth': 'depth farther than this (m) is not integrated',
    'max_blocks': 'most voxel blocks held in memory (the cap: 10 KiB each at 8^3 voxels); the blocks '
    'farthest from the camera are evicted (to the archive)',
    'block_size': 'voxels along each edge of a block',
    'min_confidence': 'pixels whose fused confidence is below this are left out; the rest are weighted '
    'by their confidence (0: the consistency test decides which pixels enter)',
    'confidence_power': "a pixel's integration weight is its confidence to this power (torch engine; "
    'Open3D weighs every pixel 1)',
    'depth_power': "a pixel's integration weight is also divided by its depth (m) to this power, so that "
    'it weighs a distance in metres (voxblox weighs 1/z^2; torch engine; 0 = the confidence alone)',
    'consistency_span': 'keyframes before and after each keyframe that its depth is checked against before '
    'integration (the map lags this many keyframes; save_map and shutdown integrate the rest); 0 = off',
    'consistency_tolerance': 'a pixel agrees with another keyframe when the depth it lands on there is '
    'within this fraction of its own',
    'consistency_views': 'other keyframes that must agree before a pixel is integrated',
    'max_weight': 'a voxel weight stops growing here (a changed scene can still overwrite it)',
    'min_weight': 'surface extraction keeps voxels observed with at least this accumulated weight (the '
    'default keeps one observation of confidence 0.045 at 2.5 m, 0.018 at 1 m)',
    'allocation_stride': 'pixel stride of the block allocation pass',
    'archive': 'evicted blocks go to a file on disk and come back when a keyframe needs them again; '
    '~/save_map and map_file hold them (torch engine; false: evicted blocks are dropped)',
    'archive_dir': "where the archive's directory is made, deleted when the map goes ('': "
    '$ROS_HOME/depth_fusion_ros/map_archive, ~/.ros by default: a disk, not the temporary directory that '
    'some systems keep in memory)',
    'archive_max_mb': 'most disk the archive takes (MiB); blocks evicted past it are lost (counted)',
    'engine': 'TSDF engine: auto (Open3D when installed, else torch), torch, or open3d (falls back to '
    'torch with one log line when Open3D is missing)',
}
