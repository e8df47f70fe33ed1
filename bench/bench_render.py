"""Benchmark: synthetic RGB-D rendering time per frame (rfm_core.sim), on one core.

Rooms with exactly 30 objects, a handheld trajectory, noise on. Reports the median time
per frame at 320x240 and 640x480 with projected-rectangle culling (the default) and,
as the baseline measured in the same run, without it (every pixel against every box); and
the same rooms in the realistic world (furniture made of parts, clutter, the realsense
sensor model: ``rfm sim --furniture parts --clutter --sensor realsense``) against the
solid-box rooms with today's default noise.

    ros_ws/env.sh python bench/bench_render.py [--frames 20]
"""
import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'          # one core, before numpy loads

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from rfm_core.observations import CameraIntrinsics  # noqa: E402
from rfm_core.sim.render import NoiseModel, Renderer  # noqa: E402
from rfm_core.sim.room import generate_room  # noqa: E402
from rfm_core.sim.trajectory import make_trajectory  # noqa: E402


def per_frame_ms(renderer, traj, frames):
    rng = np.random.default_rng(0)
    times = []
    for i in range(frames):
        start = time.perf_counter()
        renderer.render(traj.rotations[i], traj.positions[i], rng)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=20)
    parser.add_argument('--rooms', type=int, default=3)
    args = parser.parse_args()
    print(f'# render time per frame, rooms with 30 objects, median over {args.rooms} rooms x '
          f'{args.frames} frames, one core (numpy {np.__version__})')
    print('| size | culled (ms) | baseline: no culling (ms) | speed-up | realistic world (ms) | realistic / culled |')
    print('|---|---|---|---|---|---|')
    for w, h in ((320, 240), (640, 480)):
        f = w / 2 / np.tan(np.radians(35))
        intr = CameraIntrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
        culled, full, real = [], [], []
        for seed in range(args.rooms):
            room = generate_room(100 + seed, 'textured', num_objects=(30, 30))
            assert len(room.objects) == 30
            realistic = generate_room(100 + seed, 'textured', num_objects=(30, 30), furniture='parts', clutter=True)
            traj = make_trajectory(room, 'handheld', args.frames, fps=10, seed=seed)
            culled.append(per_frame_ms(Renderer(room, intr), traj, args.frames))
            full.append(per_frame_ms(Renderer(room, intr, cull=False), traj, args.frames))
            real.append(per_frame_ms(Renderer(realistic, intr, NoiseModel.realsense()), traj, args.frames))
        c, b, r = statistics.median(culled), statistics.median(full), statistics.median(real)
        print(f'| {w}x{h} | {c:.1f} | {b:.1f} | {b / c:.1f}x | {r:.1f} | {r / c:.2f}x |')


if __name__ == '__main__':
    main()
