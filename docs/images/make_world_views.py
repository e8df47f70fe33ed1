"""Colour | depth views of the simulator's realistic world (furniture made of parts, clutter).

    source ros_ws/env.sh && python docs/images/make_world_views.py    # writes docs/images/world_parts.png

Each row looks at one kind of object of a room (seed 5004, textured, parts + clutter) from
2.2 m in front of it at 1.3 m height; depth is grey up to 6 m. Rendered without sensor noise
so the geometry is easy to see (and the file small).
"""
from pathlib import Path

import numpy as np

from rfm_core.io.png import write_png
from rfm_core.sim.capture import Capture, CaptureConfig
from rfm_core.sim.render import NoiseModel, Renderer

OUT = Path(__file__).resolve().parent / 'world_parts.png'
LABELS = ('bookshelf', 'table', 'sofa', 'plant')


def look_at(eye, target):
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], 1)


def main():
    config = CaptureConfig(seed=5004, room_style='textured', frames=1, furniture='parts', clutter=True)
    capture = Capture(config)
    renderer = Renderer(capture.room, config.intrinsics, NoiseModel.none())
    rows = []
    for label in LABELS:
        obj = next(o for o in capture.room.objects if o.label == label)
        centre, yaw = obj.box[:3], obj.box[6]
        eye = centre + 2.2 * np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        eye = np.r_[np.clip(eye[:2], 0.3, capture.room.size[:2] - 0.3), 1.3]
        out = renderer.render(look_at(eye, centre), eye)
        grey = np.clip(np.nan_to_num(out.depth) / 6.0 * 255, 0, 255).astype(np.uint8)
        rows.append(np.concatenate([out.rgb, np.repeat(grey[..., None], 3, -1)], 1))
    write_png(OUT, np.concatenate(rows, 0))
    print(f'wrote {OUT}')


if __name__ == '__main__':
    main()
