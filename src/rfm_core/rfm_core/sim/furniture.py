"""Furniture made of parts, and clutter that is no object.

Real furniture is rarely a solid box: tables stand on legs, chairs have a seat and a back,
shelves are open. :func:`object_parts` gives the parts of an object as boxes in its own
frame (x along its width, y along its depth with the back at -y, z up, origin at its
centre): the renderer draws the parts, while the ground truth stays the object's one amodal
box. Free space under a table or between a chair's legs is seen through. Objects not listed
(cabinets, wardrobes, boxes, ...) stay solid.

:func:`add_clutter` adds structure that is in no ground truth: rugs, pictures on walls, door
frames, radiators and cables on the floor, so that a detector meets things it must not
report. :func:`fill_shelves` puts objects (books, boxes, vases) on the boards of open shelves.
All of it is deterministic for a room's seed and leaves the room's layout as it was.
"""
from __future__ import annotations

import numpy as np

__all__ = ['FURNITURE_STYLES', 'object_parts', 'world_parts', 'add_clutter', 'fill_shelves', 'Clutter']

FURNITURE_STYLES = ('boxes', 'parts')


def _part(x0, x1, y0, y1, z0, z1):
    """A part spanning [x0, x1] x [y0, y1] x [z0, z1] (object frame, m)."""
    return [(x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2, x1 - x0, y1 - y0, z1 - z0, 0.0]


def _legs(hx, hy, z0, z1, leg, inset):
    return [_part(sx * (hx - inset) - leg / 2, sx * (hx - inset) + leg / 2,
                  sy * (hy - inset) - leg / 2, sy * (hy - inset) + leg / 2, z0, z1)
            for sx in (-1, 1) for sy in (-1, 1)]


def _shelf_boards(sz: float) -> list:
    """Heights (from the bottom) of an open shelf's boards: bottom, top and 2-4 between."""
    count = int(np.clip(np.floor(sz / 0.38), 3, 5))
    return list(np.linspace(0.04, sz - 0.02, count + 1))


def object_parts(label: str, size) -> np.ndarray | None:
    """(P, 7) parts of an object of class ``label`` and size (sx, sy, sz), in its frame; None
    for an object drawn as its solid box."""
    sx, sy, sz = (float(v) for v in size)
    hx, hy, hz = sx / 2, sy / 2, sz / 2
    b, t = -hz, hz                                    # bottom and top z
    if label == 'table':
        top = 0.04
        parts = [_part(-hx, hx, -hy, hy, t - top, t)] + _legs(hx, hy, b, t - top, 0.05, 0.06)
    elif label == 'desk':
        top, panel = 0.035, 0.03
        parts = [_part(-hx, hx, -hy, hy, t - top, t), _part(-hx, -hx + panel, -hy, hy, b, t - top),
                 _part(hx - panel, hx, -hy, hy, b, t - top),
                 _part(-hx + panel, hx - panel, -hy, -hy + 0.02, t - top - 0.3, t - top)]   # modesty panel
    elif label in ('chair', 'stool'):
        seat_h = min(0.46, 0.55 * sz) if label == 'chair' else sz - 0.04
        parts = [_part(-hx, hx, -hy, hy, b + seat_h - 0.04, b + seat_h)] + _legs(hx, hy, b, b + seat_h - 0.04,
                                                                              0.035, 0.03)
        if label == 'chair':                          # the back, at -y (the front faces +y)
            parts.append(_part(-hx, hx, -hy, -hy + 0.04, b + seat_h, t))
    elif label == 'bookshelf':                        # open: sides, back, boards
        panel = 0.02
        parts = [_part(-hx, -hx + panel, -hy, hy, b, t), _part(hx - panel, hx, -hy, hy, b, t),
                 _part(-hx + panel, hx - panel, -hy, -hy + 0.012, b, t)]
        parts += [_part(-hx + panel, hx - panel, -hy + 0.012, hy, b + z - 0.02, b + z) for z in _shelf_boards(sz)]
    elif label in ('sofa', 'armchair'):
        seat, back, arm = 0.42 * sz / 0.85, 0.2 * sy, min(0.16, 0.2 * sx)
        parts = [_part(-hx + arm, hx - arm, -hy + back, hy, b, b + seat),            # seat
                 _part(-hx, hx, -hy, -hy + back, b, t),                              # back
                 _part(-hx, -hx + arm, -hy + back, hy, b, b + 0.75 * sz),            # arms
                 _part(hx - arm, hx, -hy + back, hy, b, b + 0.75 * sz)]
    elif label == 'bed':                              # frame, mattress, headboard (at -y, the wall)
        frame, head = 0.25, 0.06
        parts = [_part(-hx, hx, -hy + head, hy, b, b + frame),
                 _part(-hx + 0.02, hx - 0.02, -hy + head, hy - 0.02, b + frame, t - 0.15),
                 _part(-hx, hx, -hy, -hy + head, b, t)]
    elif label == 'lamp':                             # narrow base and stem under a wide shade
        parts = [_part(-0.3 * hx, 0.3 * hx, -0.3 * hy, 0.3 * hy, b, b + 0.04),
                 _part(-0.06 * hx, 0.06 * hx, -0.06 * hy, 0.06 * hy, b + 0.04, t - 0.4 * sz),
                 _part(-hx, hx, -hy, hy, t - 0.4 * sz, t)]
    elif label == 'plant':                            # a pot under the foliage
        parts = [_part(-0.55 * hx, 0.55 * hx, -0.55 * hy, 0.55 * hy, b, b + 0.35 * sz),
                 _part(-hx, hx, -hy, hy, b + 0.35 * sz, t)]
    else:
        return None
    return np.array(parts, dtype=np.float64)


def world_parts(box, parts: np.ndarray) -> np.ndarray:
    """Parts (P, 7) in an object's frame -> boxes in the map frame, for an object ``box``."""
    c, s = np.cos(box[6]), np.sin(box[6])
    out = parts.copy()
    out[:, 0] = box[0] + c * parts[:, 0] - s * parts[:, 1]
    out[:, 1] = box[1] + s * parts[:, 0] + c * parts[:, 1]
    out[:, 2] = box[2] + parts[:, 2]
    out[:, 6] = box[6] + parts[:, 6]
    return out


class Clutter:
    """Structure that is no object: a box in the map frame with a material and a kind."""

    def __init__(self, box, kind: str, material):
        self.box = np.asarray(box, dtype=np.float64)
        self.kind = kind
        self.material = material


def _clear_of(box, boxes, margin=0.02) -> bool:
    """Whether ``box`` (any yaw) keeps out of ``boxes`` (their bounding circles, 3D)."""
    if not len(boxes):
        return True
    boxes = np.asarray(boxes)
    r = np.hypot(box[3], box[4]) / 2 + np.hypot(boxes[:, 3], boxes[:, 4]) / 2 + margin
    near = np.hypot(*(boxes[:, :2] - box[:2]).T) < r
    overlap_z = np.abs(boxes[:, 2] - box[2]) < (boxes[:, 5] + box[5]) / 2 + margin
    return not np.any(near & overlap_z)


def add_clutter(room, rng: np.random.Generator, make_material) -> list:
    """Rugs, pictures, door frames, radiators and cables for ``room`` (not in its ground
    truth): a list of :class:`Clutter`. ``make_material(kind)`` gives each its material."""
    w, d, h = room.size
    objects = room.boxes
    out = []

    def on_wall(width, height, depth, z, kind, tries=20):
        for _ in range(tries):
            wall = int(rng.integers(4))
            along = rng.uniform(width / 2 + 0.1, (w if wall < 2 else d) - width / 2 - 0.1)
            xy = [(along, depth / 2), (along, d - depth / 2), (depth / 2, along), (w - depth / 2, along)][wall]
            yaw = [0.0, np.pi, -np.pi / 2, np.pi / 2][wall]
            box = np.array([xy[0], xy[1], z, width, depth, height, yaw])
            if _clear_of(box, objects) and _clear_of(box, [c.box for c in out]):
                out.append(Clutter(box, kind, make_material(kind)))
                return

    for _ in range(int(rng.integers(1, 3))):          # rugs: thin, under whatever stands there
        rw, rd = rng.uniform(1.2, 2.4), rng.uniform(0.8, 1.8)
        centre = rng.uniform([rw / 2 + 0.2, rd / 2 + 0.2], [max(w - rw / 2 - 0.2, rw / 2 + 0.21),
                                                             max(d - rd / 2 - 0.2, rd / 2 + 0.21)])
        out.append(Clutter([centre[0], centre[1], 0.006, rw, rd, 0.012, rng.uniform(-0.2, 0.2)], 'rug',
                           make_material('rug')))
    for _ in range(int(rng.integers(1, 4))):          # pictures
        pw = rng.uniform(0.3, 0.9)
        on_wall(pw, pw * rng.uniform(0.6, 1.2), 0.025, rng.uniform(1.3, 1.8), 'picture')
    for _ in range(int(rng.integers(0, 2))):          # radiators under where windows would be
        on_wall(rng.uniform(0.6, 1.2), 0.55, 0.1, 0.4, 'radiator')
    if rng.random() < 0.7:                            # a door frame: two posts and a lintel
        before = len(out)
        on_wall(0.95, 2.1, 0.06, 1.05, 'door')
        if len(out) > before:
            door = out.pop().box
            c, s = np.cos(door[6]), np.sin(door[6])
            for local_x in (-0.45, 0.45):
                out.append(Clutter([door[0] + c * local_x, door[1] + s * local_x, 1.025, 0.08, 0.06, 2.05, door[6]],
                                   'door_frame', make_material('door_frame')))
            out.append(Clutter([door[0], door[1], 2.08, 0.98, 0.06, 0.08, door[6]], 'door_frame',
                               make_material('door_frame')))
    for _ in range(int(rng.integers(0, 3))):          # cables on the floor
        length = rng.uniform(0.8, 2.0)
        centre = rng.uniform([0.5, 0.5], [w - 0.5, d - 0.5])
        out.append(Clutter([centre[0], centre[1], 0.006, length, 0.012, 0.012, rng.uniform(-np.pi, np.pi)],
                           'cable', make_material('cable')))
    return out


def fill_shelves(room, rng: np.random.Generator, make_object) -> None:
    """Objects on the boards of the room's open shelves (books, boxes, vases: each a ground-
    truth object). ``make_object(label, box)`` adds one."""
    for obj in list(room.objects):
        if obj.label != 'bookshelf' or obj.parts is None:
            continue
        box = obj.box
        sx, sy, sz = box[3:6]
        boards = _shelf_boards(sz)
        c, s = np.cos(box[6]), np.sin(box[6])
        for lower, upper in zip(boards[:-1], boards[1:]):
            clear = upper - lower - 0.04
            x = -sx / 2 + 0.04
            while x < sx / 2 - 0.12 and clear > 0.1:
                label = ('books', 'box', 'vase')[int(rng.integers(3))]
                ow = rng.uniform(0.08, 0.3)
                od = min(rng.uniform(0.12, 0.3), sy - 0.05)
                oh = min(rng.uniform(0.1, 0.3), clear)
                if x + ow > sx / 2 - 0.03:
                    break
                if rng.random() < 0.7:
                    lx, ly = x + ow / 2, -sy / 2 + 0.02 + od / 2
                    make_object(label, np.array([box[0] + c * lx - s * ly, box[1] + s * lx + c * ly,
                                                 box[2] - sz / 2 + lower + oh / 2, ow, od, oh, box[6]]))
                x += ow + rng.uniform(0.02, 0.15)
