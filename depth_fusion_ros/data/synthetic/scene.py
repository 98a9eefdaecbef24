"""Synthetic indoor scenes: a room with boxes and tables, materials, and a light.

A scene is a list of (optionally yawed) boxes. Object 0 is the room itself, seen from the
inside (rays *exit* it); every other object is a solid box (rays *enter* it). Tables are a
top slab plus four legs, each its own box. Each object has six faces, and each face
(a "surface", index ``object * 6 + face``) carries its own texture placement, so faces of
one box do not repeat the same pattern.

Face codes: ``face = 2 * axis + (normal points to +axis)``, in the object's local frame;
0: -x, 1: +x, 2: -y, 3: +y, 4: -z, 5: +z. For the room the normal points inwards, so the
floor is face 5 and the ceiling face 4.

The layout is seeded and keeps every box away from the camera path, so a camera is never
inside (or right against) a box.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .config import SynthConfig
from .texture import PATTERNS, PERIOD_TEXELS, TextureAtlas, periodic_albedo, random_colour, textured_albedo
from .trajectory import Trajectory
from .walkers import WALKER_HALF, walker_centres, walker_yaw

log = logging.getLogger(__name__)

#: Minimum distance (m) between any camera position and any box.
CAMERA_CLEARANCE = 0.9
#: Gap (m) between footprints of floor-standing furniture.
FURNITURE_GAP = 0.12
#: Room faces in face-code order (named by where they are: face 0 has its inward normal
#: along -x, so it is the wall at +x), for material groups and names.
ROOM_FACES = ('wall_+x', 'wall_-x', 'wall_+y', 'wall_-y', 'ceiling', 'floor')


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about the world z axis (box-to-world)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Furniture:
    """One box of the layout before it becomes scene arrays."""

    name: str
    centre: np.ndarray
    half: np.ndarray
    yaw: float
    group: str  # material group: boxes are one group each; a table has 'top' and 'legs'

    @property
    def world_half(self) -> np.ndarray:
        """Half extents of the world-axis-aligned bounding box."""
        return np.abs(yaw_matrix(self.yaw)) @ self.half


@dataclass
class Scene:
    """Everything the renderer needs; arrays are indexed by object or by surface."""

    room: np.ndarray  # (3,) W, D, H
    centres: np.ndarray  # (n, 3)
    halves: np.ndarray  # (n, 3)
    rotations: np.ndarray  # (n, 3, 3) box-to-world
    names: list[str]
    groups: list[str]  # material group of each object
    surface_texture: np.ndarray  # (n * 6,) texture id in the atlas
    surface_textured: np.ndarray  # (n * 6,) bool: strongly textured vs flat albedo
    surface_offset: np.ndarray  # (n * 6, 2) float32 texel offset of the face's UV origin
    surface_texels_per_m: np.ndarray  # (n * 6,) float32
    atlas: TextureAtlas
    light: np.ndarray  # (3,) point light position
    ambient: float = 0.38
    diffuse: float = 0.85
    #: Distance (m) at which the point light has fallen to half intensity.
    falloff: float = 4.0
    _corners: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_objects(self) -> int:
        return len(self.names)

    def corners(self) -> np.ndarray:
        """(n, 8, 3) world corners of every object (for screen-space culling)."""
        if self._corners is None:
            signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing='ij')).reshape(3, 8).T
            local = signs[None] * self.halves[:, None, :]
            self._corners = np.einsum('nij,nkj->nki', self.rotations, local) + self.centres[:, None, :]
        return self._corners

    def surface_name(self, surface: int) -> str:
        obj, face = divmod(int(surface), 6)
        if obj == 0:
            return ROOM_FACES[face]
        return f'{self.names[obj]}/{"-+"[face % 2]}{"xyz"[face // 2]}'


def _aabb_point_distance(centre: np.ndarray, half: np.ndarray, points: np.ndarray) -> float:
    """Smallest distance from ``points`` (N, 3) to an axis-aligned box."""
    outside = np.maximum(np.abs(points - centre) - half, 0.0)
    return float(np.min(np.linalg.norm(outside, axis=1)))


def _footprints_overlap(a: Furniture, b: Furniture, gap: float) -> bool:
    ha, hb = a.world_half, b.world_half
    return bool(np.all(np.abs(a.centre[:2] - b.centre[:2]) < ha[:2] + hb[:2] + gap))


class _Layout:
    """Rejection-sampling placement of furniture in the room, in view of the camera."""

    def __init__(self, room: np.ndarray, trajectory: Trajectory, rng: np.random.Generator) -> None:
        self.room = room
        self.trajectory = trajectory
        self.rng = rng
        self.floor_items: list[Furniture] = []
        self.items: list[Furniture] = []

    def _clear_of_camera(self, item: Furniture) -> bool:
        return (
            _aabb_point_distance(item.centre, item.world_half, self.trajectory.positions) >= CAMERA_CLEARANCE
        )

    def _inside_room(self, item: Furniture) -> bool:
        half = item.world_half
        return bool(np.all(np.abs(item.centre[:2]) + half[:2] <= self.room[:2] / 2 - 0.03))

    def _sample_floor_xy(self, half: np.ndarray) -> np.ndarray:
        """Mostly inside the camera's view cone (towards the look-at point), sometimes anywhere."""
        W, D, _ = self.room
        origin, target = self.trajectory.view_origin, self.trajectory.view_target
        if self.rng.uniform() < 0.8:
            y = self.rng.uniform(origin[1] + 1.0, D / 2 - half[1])
            spread = 0.35 + 0.5 * (y - origin[1])
            x = target[0] + self.rng.uniform(-spread, spread)
        else:
            x = self.rng.uniform(-W / 2 + half[0], W / 2 - half[0])
            y = self.rng.uniform(-D / 2 + half[1], D / 2 - half[1])
        return np.array([x, y])

    def place_on_floor(self, name: str, half: np.ndarray, yaw: float, parts) -> bool:
        """Place an object of local half extents ``half``; ``parts(centre_xy)`` returns its
        boxes. Returns False when no free spot was found (the object is skipped)."""
        probe = Furniture(name, np.zeros(3), half, yaw, name)
        for _ in range(200):
            probe.centre = np.array([*self._sample_floor_xy(probe.world_half), half[2]])
            if not self._inside_room(probe) or not self._clear_of_camera(probe):
                continue
            if any(_footprints_overlap(probe, other, FURNITURE_GAP) for other in self.floor_items):
                continue
            boxes = parts(probe.centre)
            if not all(self._clear_of_camera(b) for b in boxes):
                continue
            self.floor_items.append(probe)
            self.items.extend(boxes)
            return True
        log.debug('no free spot for %s, skipped', name)
        return False

    def place_on_table(self, name: str, half: np.ndarray, yaw: float, table: Furniture) -> bool:
        top = table.centre[2] + table.half[2]
        room_left = table.world_half[:2] - np.abs(yaw_matrix(yaw)[:2, :2]) @ half[:2] - 0.03
        if np.any(room_left <= 0):
            return False
        for _ in range(50):
            xy = table.centre[:2] + self.rng.uniform(-room_left, room_left)
            box = Furniture(name, np.array([*xy, top + half[2]]), half, yaw, name)
            if not self._clear_of_camera(box):
                continue
            others = [b for b in self.items if b.centre[2] - b.half[2] >= top - 1e-6]
            if any(_footprints_overlap(box, o, 0.03) for o in others):
                continue
            self.items.append(box)
            return True
        return False


def _table_parts(name: str, half: np.ndarray, yaw: float, centre: np.ndarray) -> list[Furniture]:
    """Top slab and four legs of a table whose bounding box has half extents ``half``."""
    thickness, leg = 0.02, 0.025
    height = 2 * half[2]
    top_centre = np.array([*centre[:2], height - thickness])
    top = Furniture(f'{name}_top', top_centre, np.array([*half[:2], thickness]), yaw, f'{name}_top')
    R = yaw_matrix(yaw)
    legs = []
    leg_half_h = (height - 2 * thickness) / 2
    for i, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
        offset = R @ np.array([sx * (half[0] - 0.04), sy * (half[1] - 0.04), 0.0])
        legs.append(
            Furniture(
                f'{name}_leg{i}',
                np.array([*(centre[:2] + offset[:2]), leg_half_h]),
                np.array([leg, leg, leg_half_h]),
                yaw,
                f'{name}_legs',
            )
        )
    return [top, *legs]


def layout_furniture(
    cfg: SynthConfig, room: np.ndarray, trajectory: Trajectory, rng: np.random.Generator
) -> list[Furniture]:
    """Seeded tables, floor boxes and boxes standing on tables, clear of the camera path."""
    layout = _Layout(room, trajectory, rng)
    tables = []
    for i in range(cfg.tables):
        half = np.array([rng.uniform(0.4, 0.7), rng.uniform(0.3, 0.45), rng.uniform(0.36, 0.39)])
        yaw = float(rng.choice((0.0, np.pi / 2)))
        name = f'table{i}'
        if layout.place_on_floor(name, half, yaw, lambda c, n=name, h=half, y=yaw: _table_parts(n, h, y, c)):
            tables.append(next(b for b in layout.items if b.name == f'{name}_top'))
    for i in range(cfg.boxes):
        name = f'box{i}'
        yaw = float(rng.uniform(-np.pi / 4, np.pi / 4)) if rng.uniform() < 0.3 else 0.0
        if tables and rng.uniform() < 0.35:
            half = np.array([rng.uniform(0.08, 0.2), rng.uniform(0.08, 0.2), rng.uniform(0.06, 0.2)])
            table = tables[int(rng.integers(len(tables)))]
            if layout.place_on_table(name, half, yaw, table):
                continue
        half = np.array([rng.uniform(0.15, 0.45), rng.uniform(0.15, 0.45), rng.uniform(0.15, 0.6)])
        layout.place_on_floor(name, half, yaw, lambda c, n=name, h=half, y=yaw: [Furniture(n, c, h, y, n)])
    return layout.items


def _assign_materials(
    cfg: SynthConfig, groups: list[str], rng: np.random.Generator
) -> tuple[dict[str, int], list[np.ndarray], dict[str, bool], dict[str, float]]:
    """One texture per material group: a random pattern, or a flat colour for the chosen
    texture-less fraction. The floor always stays textured (real floors are, and a scene
    without a textured floor is a poor multi-view test)."""
    candidates = [g for g in groups if g != 'floor']
    n_flat = round(cfg.textureless_fraction * len(groups))
    flat = set(rng.permutation(candidates)[: min(n_flat, len(candidates))].tolist())
    texture_of, textures, textured, texel_size = {}, [], {}, {}
    for g in groups:
        texture_of[g] = len(textures)
        textured[g] = g not in flat
        if g in flat:
            textures.append(random_colour(rng, (0.3, 0.85))[None, None, :])
            texel_size[g] = 1.0
            continue
        large = g in ROOM_FACES or g.endswith('_top')
        if cfg.texture_period:  # one motif per period: texels sized so that it spans the period
            albedo = periodic_albedo(rng, 512 if large else 256)
            texel_size[g] = cfg.texture_period / PERIOD_TEXELS * rng.uniform(0.8, 1.25)
        else:
            albedo = textured_albedo(rng, str(rng.choice(PATTERNS)), 512 if large else 256)
            texel_size[g] = (0.004 if g in ROOM_FACES else 0.003) * rng.uniform(0.8, 1.25)
        if cfg.texture_contrast != 1.0:  # faint texture: same pattern, squeezed towards its mean
            mean = albedo.mean(axis=(0, 1), keepdims=True)
            albedo = (mean + cfg.texture_contrast * (albedo - mean)).astype(np.float32)
        textures.append(albedo)
    return texture_of, textures, textured, texel_size


def build_scene(
    cfg: SynthConfig, room: np.ndarray, trajectory: Trajectory, rng: np.random.Generator
) -> Scene:
    """The seeded scene (furniture, materials, light) for a room and camera trajectory."""
    furniture = layout_furniture(cfg, room, trajectory, rng)
    if cfg.walkers:  # the last objects, so that a static room draws what it drew before
        yaw = walker_yaw(trajectory)
        furniture += [
            Furniture(f'walker{k}', centre, WALKER_HALF.copy(), yaw, f'walker{k}')
            for k, centre in enumerate(walker_centres(cfg, trajectory, 0))
        ]
    names = ['room', *(f.name for f in furniture)]
    groups_of_objects = ['room', *(f.group for f in furniture)]
    groups = list(dict.fromkeys([*ROOM_FACES, *(f.group for f in furniture)]))
    texture_of, textures, textured, texel_size = _assign_materials(cfg, groups, rng)

    n = len(names)
    centres = np.array([[0.0, 0.0, room[2] / 2], *(f.centre for f in furniture)])
    halves = np.array([room / 2, *(f.half for f in furniture)])
    rotations = np.stack([np.eye(3), *(yaw_matrix(f.yaw) for f in furniture)])
    surface_group = [
        ROOM_FACES[face] if obj == 0 else groups_of_objects[obj] for obj in range(n) for face in range(6)
    ]
    tex = np.array([texture_of[g] for g in surface_group], dtype=np.int64)
    sizes = np.array([textures[t].shape[0] for t in tex], dtype=np.float64)
    offsets = (rng.uniform(0.0, 1.0, size=(n * 6, 2)) * sizes[:, None]).astype(np.float32)
    light = np.array([rng.uniform(-0.3, 0.3) * room[0], rng.uniform(-0.1, 0.3) * room[1], room[2] - 0.25])
    scene = Scene(
        room=room,
        centres=centres,
        halves=halves,
        rotations=rotations,
        names=names,
        groups=groups_of_objects,
        surface_texture=tex,
        surface_textured=np.array([textured[g] for g in surface_group]),
        surface_offset=offsets,
        surface_texels_per_m=np.array([1.0 / texel_size[g] for g in surface_group], dtype=np.float32),
        atlas=TextureAtlas.build(textures),
        light=light,
    )
    log.debug(
        'scene: room %s, %d objects, %d textures (%.1f MB)',
        np.round(room, 2),
        n,
        len(textures),
        scene.atlas.nbytes / 1e6,
    )
    return scene
