"""``depth-fusion mesh``: the mesh of a saved map file, without running map_node."""

from __future__ import annotations

import argparse
import sys

from .argtypes import at_least, subcommand

DESCRIPTION = """\
Write the surface of a map file (map_node's map_file: the TSDF with its archived blocks) as a
binary .ply mesh, offline: what ~/save_map would write from that map. The surface is extracted
in slabs of at most --max-blocks blocks, each read from the file as it is needed (map files
written before format 2 are read whole).

examples:
  depth-fusion mesh ~/maps/lab.tsdf --out lab.ply
  depth-fusion mesh ~/maps/lab.tsdf --out lab.ply --min-weight 0.5   # only well-observed voxels
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = subcommand(sub, 'mesh', 'the mesh (.ply) of a saved map file, offline', DESCRIPTION)
    p.add_argument('map_file', help='a map file written by map_node (map_file, ~/save_map)')
    p.add_argument('--out', required=True, help='the .ply to write')
    p.add_argument('--overwrite', action='store_true', help='replace the .ply if it exists')
    weight = (
        'voxels observed with less accumulated weight are left out (default: map.min_weight, for a '
        'file saved with other weights (map.confidence_power, map.depth_power) the threshold of the same '
        'single observation at 2.5 m)'
    )
    p.add_argument('--min-weight', type=float, default=None, help=weight)
    blocks = at_least(1, '--max-blocks')
    p.add_argument('--max-blocks', type=blocks, default=10000, help='most blocks extracted at once (10000)')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..mapping.config import MapConfig
    from ..mapping.map_file import file_blocks, file_min_weight, read_state
    from ..mapping.ply import write_ply
    from ..mapping.slab_surface import slab_mesh
    from .paths import OutputPathError, check_new_file

    out = Path(args.out)
    if out.suffix.lower() != '.ply':
        print(f'depth-fusion mesh: --out {out} must end in .ply', file=sys.stderr)
        return 2
    if args.min_weight is not None and not args.min_weight >= 0:
        print(f'depth-fusion mesh: --min-weight must be >= 0, got {args.min_weight}', file=sys.stderr)
        return 2
    try:
        state = read_state(args.map_file)
    except (OSError, ValueError) as exc:
        print(f'depth-fusion mesh: {exc}', file=sys.stderr)
        return 2
    try:
        check_new_file(out, '--out', args.overwrite)
    except OutputPathError as exc:
        print(f'depth-fusion mesh: {exc}', file=sys.stderr)
        return 2
    # A file saved with other weights (an earlier map.confidence_power or map.depth_power) gets the
    # default threshold of the same single observation.
    min_weight = file_min_weight(state, MapConfig()) if args.min_weight is None else args.min_weight
    grid = file_blocks(state, min_weight)

    mesh = slab_mesh(grid.coords, grid.rows, args.max_blocks)
    frame = state.get('world_frame') or '?'
    if mesh.is_empty:
        print(
            f'depth-fusion mesh: the map in {args.map_file} ({grid.coords.shape[0]} blocks) has no surface '
            f'with min weight {min_weight:g}: nothing written',
            file=sys.stderr,
        )
        return 1
    write_ply(out, mesh)
    print(f'{out}: {len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles (frame {frame!r})')
    return 0
