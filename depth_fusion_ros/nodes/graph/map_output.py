"""``depth-fusion run --save-map``: did ``map_node`` write the mesh, and how big is it?

The mesh is written by ``map_node`` itself as it stops (``save_on_shutdown``), in this process
or in its own; the runner only checks the result, so a run never says it saved a map it did
not (an empty map, a path that could not be written: map_node logs why).
"""

from __future__ import annotations

from pathlib import Path


def check_map_path(path: str | Path) -> Path:
    """``--save-map``'s path, expanded; ``ValueError`` unless it names a ``.ply`` file."""
    path = Path(path).expanduser()
    if path.suffix.lower() != '.ply':
        raise ValueError(f'--save-map {path}: the map is written as .ply')
    return path


def ply_counts(path: Path) -> tuple[int, int]:
    """(vertices, faces) from a PLY header, without reading the body."""
    counts = {'vertex': 0, 'face': 0}
    with open(path, 'rb') as f:
        for _ in range(64):
            line = f.readline().decode('ascii', 'replace').strip()
            parts = line.split()
            if len(parts) == 3 and parts[0] == 'element' and parts[1] in counts:
                counts[parts[1]] = int(parts[2])
            if line == 'end_header' or not line:
                break
    return counts['vertex'], counts['face']


def check_saved_map(path: Path, since_wall: float) -> tuple[Path | None, tuple[int, int] | None, str | None]:
    """``(file, (vertices, faces), None)`` when ``map_node`` wrote ``path`` during this run,
    else ``(None, None, why)``."""
    path = Path(path).expanduser()
    if not path.is_file() or path.stat().st_mtime < since_wall - 1.0:
        return None, None, f'map_node wrote no map to {path} (an empty map, or see its log)'
    try:
        return path, ply_counts(path), None
    except (OSError, ValueError) as exc:
        return None, None, f'{path} is not a readable PLY: {exc}'
