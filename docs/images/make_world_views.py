"""Colour | depth views of the simulator's realistic world (furniture made of parts, clutter).

    source ros_ws/env.sh && python docs/images/make_world_views.py

writes docs/images/world_parts.png: each row looks at one kind of object of a room (seed
5004, textured, parts + clutter) from 2.2 m in front of it at 1.3 m height; depth is grey up
to 6 m; without sensor noise so the geometry is easy to see (and the file small). And
docs/images/world_realsense.png: two of those views as the default sensor model and the
realsense model see them (colour | default depth | realsense depth; missing depth black).
"""
from pathlib import Path

import numpy as np

from rfm_core.io.png import write_png
from rfm_core.sim.capture import Capture, CaptureConfig
from rfm_core.sim.render import NoiseModel, Renderer
from rfm_core.sim.trajectory import look_rotation

OUT = Path(__file__).resolve().parent / 'world_parts.png'
OUT_SENSOR = Path(__file__).resolve().parent / 'world_realsense.png'
LABELS = ('bookshelf', 'table', 'sofa', 'plant')


def grey(depth):
    return np.repeat(np.clip(np.nan_to_num(depth) / 6.0 * 255, 0, 255).astype(np.uint8)[..., None], 3, -1)


def main():
    config = CaptureConfig(seed=5004, room_style='textured', frames=1, furniture='parts', clutter=True)
    capture = Capture(config)
    renderers = {model: Renderer(capture.room, config.intrinsics, noise)
                 for model, noise in (('none', NoiseModel.none()), ('default', NoiseModel()),
                                      ('realsense', NoiseModel.realsense()))}
    views = {}
    for label in LABELS:
        obj = next(o for o in capture.room.objects if o.label == label)
        centre, yaw = obj.box[:3], obj.box[6]
        eye = centre + 2.2 * np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        eye = np.r_[np.clip(eye[:2], 0.3, capture.room.size[:2] - 0.3), 1.3]
        view = look_rotation(centre - eye)
        views[label] = {m: r.render(view, eye, np.random.default_rng(1)) for m, r in renderers.items()}
    write_png(OUT, np.concatenate([np.concatenate([v['none'].rgb, grey(v['none'].depth)], 1)
                                   for v in views.values()], 0))
    write_png(OUT_SENSOR, np.concatenate([np.concatenate([v['realsense'].rgb, grey(v['default'].depth),
                                                          grey(v['realsense'].depth)], 1)
                                          for label, v in views.items() if label in ('bookshelf', 'table')], 0))
    print(f'wrote {OUT} and {OUT_SENSOR}')


if __name__ == '__main__':
    main()
