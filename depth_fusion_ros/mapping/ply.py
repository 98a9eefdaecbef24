"""Binary PLY files of a mesh (vertices with colour, triangles) or a coloured point cloud.

Written with numpy alone (no Open3D needed), read by MeshLab, CloudCompare, Blender and
Open3D. ``read_ply`` reads back what ``write_ply`` writes (tests, evaluation).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .surface import SurfaceMesh

_VERTEX = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('red', 'u1'), ('green', 'u1'), ('blue', 'u1')])
_FACE = np.dtype([('n', 'u1'), ('v', '<i4', (3,))])


def write_ply(path: str | Path, mesh: SurfaceMesh) -> Path:
    """Write ``mesh`` (no triangles: a point cloud) to ``path`` atomically; returns the path."""
    path = Path(path)
    if path.suffix.lower() != '.ply':
        raise ValueError(f'{path}: the map is written as .ply')
    path.parent.mkdir(parents=True, exist_ok=True)
    vertices = np.zeros(len(mesh.vertices), _VERTEX)
    for i, name in enumerate('xyz'):
        vertices[name] = mesh.vertices[:, i]
    for i, name in enumerate(('red', 'green', 'blue')):
        vertices[name] = mesh.colours[:, i]
    faces = np.zeros(len(mesh.triangles), _FACE)
    faces['n'] = 3
    faces['v'] = mesh.triangles
    header = (
        'ply\nformat binary_little_endian 1.0\ncomment depth_fusion_ros TSDF map (world frame, metres)\n'
        f'element vertex {len(vertices)}\n'
        'property float x\nproperty float y\nproperty float z\n'
        'property uchar red\nproperty uchar green\nproperty uchar blue\n'
        f'element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n'
    )
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f'.{path.name}.', suffix='.tmp')
    try:
        with os.fdopen(fd, 'wb') as f:
            f.write(header.encode('ascii'))
            f.write(vertices.tobytes())
            f.write(faces.tobytes())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it private; a map is an ordinary file
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_ply(path: str | Path) -> SurfaceMesh:
    """Read a PLY written by :func:`write_ply` (``ValueError`` for anything else)."""
    data = Path(path).read_bytes()
    end = data.find(b'end_header\n')
    if not data.startswith(b'ply\n') or end < 0:
        raise ValueError(f'{path}: not a PLY file')
    header = data[:end].decode('ascii').splitlines()
    if 'format binary_little_endian 1.0' not in header:
        raise ValueError(f'{path}: only binary little-endian PLY written by depth_fusion_ros is read')
    counts = {line.split()[1]: int(line.split()[2]) for line in header if line.startswith('element ')}
    offset = end + len(b'end_header\n')
    nv, nf = counts.get('vertex', 0), counts.get('face', 0)
    vertices = np.frombuffer(data, _VERTEX, nv, offset)
    faces = np.frombuffer(data, _FACE, nf, offset + nv * _VERTEX.itemsize)
    xyz = np.stack([vertices[c] for c in 'xyz'], axis=1).astype(np.float32)
    rgb = np.stack([vertices[c] for c in ('red', 'green', 'blue')], axis=1).astype(np.uint8)
    return SurfaceMesh(xyz, faces['v'].astype(np.int64).reshape(-1, 3), rgb)
