"""Mapping: a bounded TSDF that integrates the fused keyframe depth into one world-frame map.

No ROS import here (``nodes/map_node.py`` is the ROS side). Engines: a compact torch TSDF
(``torch_tsdf``, always available, CPU or CUDA) and Open3D's VoxelBlockGrid (``open3d_tsdf``,
optional); ``engine.make_map`` picks one. ``surface`` extracts the mesh (surface nets),
``ply`` writes it, ``scoring`` compares a map with a reference map, ``render`` draws it.
"""

from .config import ENGINES, MapConfig
from .engine import TSDFMap, make_map
from .ply import read_ply, write_ply
from .surface import SurfaceMesh

__all__ = ['ENGINES', 'MapConfig', 'SurfaceMesh', 'TSDFMap', 'make_map', 'read_ply', 'write_ply']
