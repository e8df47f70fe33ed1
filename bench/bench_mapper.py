"""Benchmark: mapper (incremental averaging) cost per keyframe as the map grows, and the
memory of the map per object.

Synthetic view graphs (a camera walking through a building: edges to the next 5 keyframes
plus loop edges, 0.2 deg / 1 cm edge noise) are fed keyframe by keyframe into an
IncrementalAverager; reported is the median and 95th percentile wall time of one update
around 100, 1000 and 5000 keyframes, and how many updates were full re-solves.

Memory per object: a map file of a simulated room (ground_truth:rgbd detections, 32-d
embeddings) divided by its number of object tracks, and per keyframe.

    ros_ws/env.sh python bench/bench_mapper.py
"""
import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from rfm_core.evaluation.pipeline import run_capture  # noqa: E402
from rfm_core.mapping.averaging import IncrementalAverager  # noqa: E402
from rfm_core.mapping.map_io import save_map  # noqa: E402
from rfm_core.mapping.synthetic import synthetic_view_graph  # noqa: E402
from rfm_core.sim.capture import CaptureConfig  # noqa: E402


def main():
    sizes = (100, 1000, 5000)
    _, edges, _ = synthetic_view_graph(max(sizes) + 50, seed=1, neighbours=5, loops=0.2,
                                       yaw_noise_deg=0.2, translation_noise_m=0.01)
    by_target = {}
    for e in edges:
        by_target.setdefault(max(e[0], e[1]), []).append(e)
    inc = IncrementalAverager()
    times, kinds = {}, {}
    for k in range(max(sizes) + 50):
        inc.add_keyframe(k)
        for s, t, pose, w in by_target.get(k, []):
            inc.add_edge(s, t, pose, w)
        start = time.perf_counter()
        stats = inc.update()
        elapsed = time.perf_counter() - start
        for size in sizes:
            if size <= k < size + 50:
                times.setdefault(size, []).append(elapsed)
                kinds.setdefault(size, []).append(stats.kind)
    print('# mapper (incremental averaging) cost per keyframe, one core')
    print('| keyframes in map | median (ms) | p95 (ms) | full re-solves in 50 updates |')
    print('|---|---|---|---|')
    for size in sizes:
        t = sorted(times[size])
        print(f'| {size} | {1e3 * statistics.median(t):.1f} | {1e3 * t[int(0.95 * (len(t) - 1))]:.1f} | '
              f'{kinds[size].count("full")} |')
    result = run_capture(CaptureConfig(seed=300, frames=60, fps=5), 'ground_truth:rgbd', noise_seed=0)
    mapper = result.mapper
    with tempfile.TemporaryDirectory() as tmp:
        size = save_map(mapper, Path(tmp) / 'map.rfm').stat().st_size
    tracks = len(mapper.tracks())
    print(f'\nmap file of a simulated room: {size / 1e3:.0f} kB for {len(mapper.keyframes)} keyframes and '
          f'{tracks} objects: {size / max(tracks, 1) / 1e3:.1f} kB per object, '
          f'{size / max(len(mapper.keyframes), 1) / 1e3:.1f} kB per keyframe')


if __name__ == '__main__':
    main()
