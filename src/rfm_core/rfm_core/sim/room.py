"""Procedural furnished rooms: gravity-aligned boxes with materials.

A room spans [0, width] x [0, depth] x [0, height] in the map frame (z up). Furniture
stands on the floor, against walls or free with a random yaw; chairs stand around tables
and desks; small objects stand on tables, desks, cabinets and shelves. Some objects come in
groups of identical copies (same size and colour: chairs, nightstands, stools, boxes) so
that appearance alone cannot tell them apart. Everything is deterministic for a seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from rfm_core.geometry import BOX_DIM, bev_corners, iou_3d
from rfm_core.sim.furniture import FURNITURE_STYLES, add_clutter, fill_shelves, object_parts

__all__ = ['STYLES', 'Material', 'RoomObject', 'Room', 'generate_room']

#: Room styles. ``plain``: uniformly painted walls and mostly untextured furniture, like
#: most real rooms (hard for point-based SfM); ``textured``: wallpaper, wood grain, fabric.
STYLES = ('plain', 'textured')


@dataclass(frozen=True)
class Material:
    """Surface appearance, fixed in object coordinates (view-consistent)."""

    color: tuple               #: base albedo, RGB in [0, 1]
    texture: str = 'plain'     #: plain, wood, fabric, checker, noise
    scale_m: float = 0.1       #: texture feature size (m)
    contrast: float = 0.0      #: modulation depth in [0, 1]
    seed: int = 0              #: seed of the texture's value noise


@dataclass(frozen=True)
class RoomObject:
    """One object: a gravity-aligned box [cx, cy, cz, sx, sy, sz, yaw] in the map frame."""

    box: np.ndarray
    label: str
    material: Material
    group: int = -1            #: objects with the same group >= 0 are identical copies
    parts: np.ndarray | None = None   #: (P, 7) parts in the object's frame (None: a solid box)


@dataclass
class Room:
    size: np.ndarray                      #: (width, depth, height) in m
    objects: list = field(default_factory=list)
    walls: tuple = ()                     #: 6 Materials: x=0, x=W, y=0, y=D, floor, ceiling
    style: str = 'plain'
    seed: int = 0
    clutter: list = field(default_factory=list)   #: structure in no ground truth (sim.furniture.Clutter)

    @property
    def boxes(self) -> np.ndarray:
        """(N, 7) boxes of all objects."""
        return np.array([o.box for o in self.objects]).reshape(-1, BOX_DIM)

    @property
    def labels(self) -> list:
        return [o.label for o in self.objects]

    def contains_camera(self, position, margin: float = 0.15) -> bool:
        """Whether a point is inside (or within ``margin`` of) any object or outside the room."""
        p = np.asarray(position, dtype=np.float64)
        if np.any(p < margin) or np.any(p > self.size - margin):
            return True
        for obj in self.objects:
            c, s, yaw = obj.box[:3], obj.box[3:6], obj.box[6]
            d = p - c
            local = np.array([np.cos(yaw) * d[0] + np.sin(yaw) * d[1],
                              -np.sin(yaw) * d[0] + np.cos(yaw) * d[1], d[2]])
            if np.all(np.abs(local) <= s / 2 + margin):
                return True
        return False


# label: (size min, size max, placement, can support small objects)
_FURNITURE = {
    'bed': ((1.4, 1.95, 0.45), (1.9, 2.2, 0.6), 'wall', False),
    'sofa': ((1.6, 0.8, 0.75), (2.4, 1.0, 0.9), 'wall', False),
    'table': ((0.8, 0.7, 0.7), (1.8, 1.0, 0.78), 'free', True),
    'desk': ((1.0, 0.55, 0.72), (1.6, 0.8, 0.78), 'wall', True),
    'cabinet': ((0.6, 0.4, 0.7), (1.2, 0.6, 1.2), 'wall', True),
    'bookshelf': ((0.6, 0.28, 1.6), (1.0, 0.4, 2.0), 'wall', False),
    'wardrobe': ((0.9, 0.55, 1.9), (1.6, 0.65, 2.2), 'wall', False),
    'tv_stand': ((1.2, 0.4, 0.45), (1.8, 0.5, 0.6), 'wall', True),
    'armchair': ((0.7, 0.7, 0.75), (0.9, 0.9, 0.95), 'free', False),
    'nightstand': ((0.4, 0.35, 0.45), (0.5, 0.45, 0.6), 'wall', True),
    'stool': ((0.35, 0.35, 0.45), (0.45, 0.45, 0.65), 'free', False),
    'bin': ((0.25, 0.25, 0.3), (0.35, 0.35, 0.45), 'free', False),
    'plant': ((0.3, 0.3, 0.5), (0.45, 0.45, 1.1), 'free', False),
}
_CHAIR = ((0.42, 0.45, 0.8), (0.5, 0.52, 1.0))
_SMALL = {
    'lamp': ((0.18, 0.18, 0.3), (0.3, 0.3, 0.55)),
    'box': ((0.15, 0.12, 0.1), (0.4, 0.3, 0.3)),
    'books': ((0.15, 0.2, 0.05), (0.3, 0.3, 0.25)),
    'vase': ((0.1, 0.1, 0.2), (0.2, 0.2, 0.4)),
    'monitor': ((0.45, 0.15, 0.35), (0.6, 0.2, 0.45)),
    'bowl': ((0.15, 0.15, 0.06), (0.3, 0.3, 0.12)),
    'tv': ((0.9, 0.12, 0.55), (1.3, 0.18, 0.8)),
}

_WOODS = [(0.55, 0.36, 0.2), (0.7, 0.5, 0.3), (0.4, 0.25, 0.15), (0.82, 0.68, 0.5)]
_FABRICS = [(0.3, 0.35, 0.5), (0.55, 0.2, 0.2), (0.35, 0.5, 0.35), (0.6, 0.6, 0.55),
            (0.25, 0.25, 0.28), (0.75, 0.6, 0.4)]
_PAINTS = [(0.92, 0.92, 0.9), (0.85, 0.88, 0.92), (0.93, 0.88, 0.8), (0.8, 0.85, 0.78),
           (0.95, 0.95, 0.95)]
_BRIGHTS = [(0.85, 0.2, 0.15), (0.15, 0.45, 0.8), (0.95, 0.75, 0.15), (0.2, 0.65, 0.35),
            (0.6, 0.3, 0.7), (0.1, 0.1, 0.1), (0.9, 0.9, 0.9)]
_FABRIC_LABELS = {'bed', 'sofa', 'armchair'}
_WOOD_LABELS = {'table', 'desk', 'cabinet', 'bookshelf', 'wardrobe', 'tv_stand', 'nightstand',
                'stool', 'chair'}


def _pick(rng, options):
    return tuple(options[rng.integers(len(options))])


def _material(rng, label: str, style: str) -> Material:
    """A material for an object of class ``label`` in a room of ``style``."""
    jitter = rng.uniform(-0.06, 0.06, 3)
    if label in _FABRIC_LABELS:
        color, texture, scale, contrast = _pick(rng, _FABRICS), 'fabric', 0.02, 0.25
    elif label in _WOOD_LABELS:
        color, texture, scale, contrast = _pick(rng, _WOODS + [(0.9, 0.9, 0.88)]), 'wood', 0.04, 0.35
    elif label == 'plant':
        color, texture, scale, contrast = (0.2, 0.5, 0.2), 'noise', 0.05, 0.5
    elif label in ('monitor', 'tv'):
        color, texture, scale, contrast = (0.08, 0.08, 0.1), 'plain', 0.1, 0.0
    else:
        color, texture, scale, contrast = _pick(rng, _BRIGHTS), 'checker', 0.06, 0.3
    if style == 'plain':
        contrast *= 0.15 if texture in ('wood', 'fabric') else 0.0
    color = tuple(float(c) for c in np.clip(np.asarray(color) + jitter, 0.03, 0.97))
    return Material(color, texture, scale, float(contrast), int(rng.integers(2**31)))


def _footprint_free(candidate: np.ndarray, placed: list, margin: float) -> bool:
    """No BEV overlap (with a margin) with already placed floor boxes."""
    if not placed:
        return True
    grown = candidate.copy()
    grown[3:5] += 2 * margin
    grown[2], grown[5] = 0.5, 1.0                   # compare footprints only
    others = np.array(placed)
    others[:, 2], others[:, 5] = 0.5, 1.0
    return not np.any(iou_3d(grown[None], others) > 0)


def _inside_room(box: np.ndarray, size: np.ndarray) -> bool:
    corners = bev_corners(box)
    return bool(np.all(corners >= 0.02) and np.all(corners <= size[:2] - 0.02))


def _wall_pose(rng, room_size, sx, sy):
    """Center (x, y) and yaw of a box of footprint sx x sy standing against a random wall."""
    w, d = room_size[:2]
    wall = rng.integers(4)
    gap = rng.uniform(0.02, 0.08)
    if wall == 0:     # y = 0, facing +y
        return np.array([rng.uniform(sx / 2, w - sx / 2), sy / 2 + gap]), 0.0
    if wall == 1:     # y = D, facing -y
        return np.array([rng.uniform(sx / 2, w - sx / 2), d - sy / 2 - gap]), np.pi
    if wall == 2:     # x = 0, facing +x
        return np.array([sy / 2 + gap, rng.uniform(sx / 2, d - sx / 2)]), -np.pi / 2
    return np.array([w - sy / 2 - gap, rng.uniform(sx / 2, d - sx / 2)]), np.pi / 2


def generate_room(seed: int, style: str = 'plain', num_objects: tuple = (10, 40),
                  size_range=((4.0, 3.5, 2.5), (8.0, 7.0, 3.0)), furniture: str = 'boxes',
                  clutter: bool = False) -> Room:
    """A furnished room, deterministic for ``seed``.

    ``num_objects`` bounds the total count (furniture + small objects): the generator keeps
    adding until it reaches a target drawn in that range or runs out of free space.
    ``furniture``: 'boxes' (every object a solid box) or 'parts' (tables on legs, chairs with
    backs, open shelves with objects on their boards, ...: :mod:`rfm_core.sim.furniture`);
    ``clutter``: rugs, pictures, door frames, radiators and cables that are in no ground
    truth. Both keep the room's layout: the same seed places the same furniture.
    """
    if style not in STYLES:
        raise ValueError(f'style must be one of {STYLES}, got {style!r}')
    if furniture not in FURNITURE_STYLES:
        raise ValueError(f'furniture must be one of {FURNITURE_STYLES}, got {furniture!r}')
    rng = np.random.default_rng(seed)
    size = rng.uniform(size_range[0], size_range[1])
    target = int(rng.integers(num_objects[0], num_objects[1] + 1))

    wall_paint = _pick(rng, _PAINTS)
    textured = style == 'textured'
    walls = []
    for i in range(4):
        shade = np.clip(np.asarray(wall_paint) * rng.uniform(0.97, 1.03), 0, 1)
        walls.append(Material(tuple(shade), 'checker' if textured and i % 2 else
                              ('noise' if textured else 'plain'),
                              0.25 if textured else 0.5, 0.15 if textured else 0.0,
                              int(rng.integers(2**31))))
    floor = Material(_pick(rng, _WOODS), 'wood', 0.12, 0.35 if textured else 0.08,
                     int(rng.integers(2**31)))
    ceiling = Material((0.95, 0.95, 0.95), 'plain', 1.0, 0.0, 0)
    room = Room(size=size, walls=tuple(walls) + (floor, ceiling), style=style, seed=seed)

    floor_boxes: list = []
    supports: list = []
    on_support: dict = {}        # support index -> boxes standing on it
    group_id = 0

    def place(label, box, material, group=-1, support=False):
        room.objects.append(RoomObject(np.asarray(box, dtype=np.float64), label, material, group))
        if box[2] - box[5] / 2 < 0.01:          # stands on the floor
            floor_boxes.append(np.asarray(box, dtype=np.float64))
        if support:
            supports.append(len(room.objects) - 1)

    def try_floor(label, placement, sx, sy, sz, tries=40):
        for _ in range(tries):
            if placement == 'wall':
                xy, yaw = _wall_pose(rng, size, sx, sy)
                yaw += rng.normal(0, 0.02)
            else:
                xy = rng.uniform([0.3, 0.3], size[:2] - 0.3)
                yaw = rng.uniform(-np.pi, np.pi)
            box = np.array([xy[0], xy[1], sz / 2, sx, sy, sz, yaw])
            if _inside_room(box, size) and _footprint_free(box, floor_boxes, 0.1):
                return box
        return None

    def add_furniture(candidates):
        """Furniture, big pieces first so that they find room."""
        nonlocal group_id
        order = sorted(candidates, key=lambda name: -np.prod(_FURNITURE[name][1]))
        for name in [name for name in order if rng.random() < 0.6]:
            if len(room.objects) >= target:
                break
            lo, hi, placement, support = _FURNITURE[name]
            copies = 1
            if name in ('nightstand', 'stool') or (name == 'cabinet' and rng.random() < 0.5):
                copies = int(rng.integers(2, 4))     # identical copies
            sx, sy, sz = rng.uniform(lo, hi)
            material = _material(rng, name, style)
            group = group_id if copies > 1 else -1
            group_id += copies > 1
            box = None
            for _ in range(copies):
                candidate = try_floor(name, placement, sx, sy, sz)
                if candidate is not None and len(room.objects) < target:
                    box = candidate
                    place(name, box, material, group, support)
            # Chairs around tables and desks: identical copies facing the table.
            if name in ('table', 'desk') and box is not None:
                chair_size = rng.uniform(*_CHAIR)
                chair_mat = _material(rng, 'chair', style)
                sides = [0, 1, 2, 3] if name == 'table' else [0]
                count = int(rng.integers(1, len(sides) + 1)) if name == 'table' else 1
                placed_chairs = 0
                for side in rng.permutation(sides)[:count]:
                    local_dir = [np.array([0.0, -1.0]), np.array([0.0, 1.0]),
                                 np.array([-1.0, 0.0]), np.array([1.0, 0.0])][side]
                    half = (box[4] / 2 if side < 2 else box[3] / 2)
                    offset = local_dir * (half + chair_size[1] / 2 - 0.1)
                    c, s = np.cos(box[6]), np.sin(box[6])
                    world = np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]])
                    facing = np.arctan2(-world[1], -world[0]) - np.pi / 2
                    chair = np.array([box[0] + world[0], box[1] + world[1], chair_size[2] / 2,
                                      *chair_size, facing])
                    # A chair may stand partly under its own table, not in anything else.
                    others = [b for b in floor_boxes if not np.array_equal(b, box)]
                    if (_inside_room(chair, size) and len(room.objects) < target
                            and _footprint_free(chair, others, 0.02)):
                        place('chair', chair, chair_mat, group_id)
                        placed_chairs += 1
                group_id += placed_chairs > 0

    def add_small_objects():
        """Small objects on supports (some identical copies)."""
        nonlocal group_id
        small_labels = list(_SMALL)
        for index in rng.permutation(supports):
            base = room.objects[index].box
            top = base[2] + base[5] / 2
            on_this = on_support.setdefault(index, [])
            for _ in range(int(rng.integers(1, 4))):
                if len(room.objects) >= target:
                    break
                name = small_labels[rng.integers(len(small_labels))]
                if name == 'tv' and room.objects[index].label != 'tv_stand':
                    name = 'box'
                lo, hi = _SMALL[name]
                sx, sy, sz = np.minimum(rng.uniform(lo, hi), [base[3] * 0.9, base[4] * 0.9, 1.0])
                material = _material(rng, name, style)
                copies = 2 if name in ('box', 'books', 'bowl') and rng.random() < 0.4 else 1
                group = group_id if copies > 1 else -1
                group_id += copies > 1
                for _ in range(copies):
                    for _attempt in range(20):
                        lx = rng.uniform(-(base[3] - sx) / 2, (base[3] - sx) / 2)
                        ly = rng.uniform(-(base[4] - sy) / 2, (base[4] - sy) / 2)
                        c, s = np.cos(base[6]), np.sin(base[6])
                        yaw = base[6] + (rng.normal(0, 0.3) if name not in ('tv', 'monitor') else 0.0)
                        box = np.array([base[0] + c * lx - s * ly, base[1] + s * lx + c * ly,
                                        top + sz / 2, sx, sy, sz, yaw])
                        if _footprint_free(box, on_this, 0.02) and len(room.objects) < target:
                            room.objects.append(RoomObject(box, name, material, group))
                            on_this.append(box)
                            break

    # Unique pieces once; then repeatable ones and small objects until the target is met.
    add_furniture(list(_FURNITURE))
    add_small_objects()
    repeatable = ['cabinet', 'bookshelf', 'armchair', 'stool', 'bin', 'plant', 'table']
    for _ in range(6):
        if len(room.objects) >= target:
            break
        before = len(room.objects)
        add_furniture(repeatable)
        add_small_objects()
        if len(room.objects) == before:
            break
    # the realistic world, from a stream of its own (the layout above stays the seed's)
    extra = np.random.default_rng([seed, 1717])
    if furniture == 'parts':
        room.objects = [replace(o, parts=object_parts(o.label, o.box[3:6])) for o in room.objects]
        fill_shelves(room, extra, lambda label, box: room.objects.append(
            RoomObject(box, label, _material(extra, label, style))))
    if clutter:
        room.clutter = add_clutter(room, extra, lambda kind: _clutter_material(extra, kind, style))
    return room


def _clutter_material(rng, kind: str, style: str) -> Material:
    """Rugs are fabric, pictures colourful, radiators and door frames painted, cables dark."""
    if kind == 'rug':
        return Material(_pick(rng, _FABRICS), 'fabric', 0.03, 0.3 if style == 'textured' else 0.1,
                        int(rng.integers(2**31)))
    if kind == 'picture':
        return Material(_pick(rng, _BRIGHTS), 'checker', 0.08, 0.5, int(rng.integers(2**31)))
    if kind == 'cable':
        return Material((0.08, 0.08, 0.08), 'plain', 0.1, 0.0, 0)
    return Material((0.93, 0.93, 0.92), 'plain', 0.1, 0.0, 0)
