"""Micro-benchmark: pairwise oriented 3D IoU and GIoU, N = M = 100 boxes.

Baseline, measured in the same run: the same exact IoU computed one pair at a time in a
Python loop (what a naive caller would write). Reports medians of repeated runs and the
speed-up against that baseline.

    ros_ws/env.sh python bench/bench_iou.py [--repeats 7]
"""
import argparse
import platform
import statistics
import time

import numpy as np

from rfm_core.geometry import giou_3d, iou_3d, iou_3d_paired


def scene_boxes(rng, n):
    """Boxes of a furnished room: 0.1-2 m objects spread over a 6 x 5 x 2.5 m volume."""
    return np.c_[rng.uniform([0, 0, 0], [6, 5, 2.5], (n, 3)), rng.uniform(0.1, 2.0, (n, 3)),
                 rng.uniform(-np.pi, np.pi, n)]


def dense_boxes(rng, n):
    """Worst case: boxes packed in a 4 m cube, so most pairs overlap."""
    return np.c_[rng.uniform(-2, 2, (n, 3)), rng.uniform(0.2, 2.0, (n, 3)),
                 rng.uniform(-np.pi, np.pi, n)]


def median_seconds(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def loop_baseline(a, b):
    return np.array([[iou_3d_paired(x, y)[0] for y in b] for x in a])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--n', type=int, default=100)
    parser.add_argument('--repeats', type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f'# pairwise IoU, N = M = {args.n}, median of {args.repeats} runs '
          f'({platform.processor() or platform.machine()}, numpy {np.__version__})')
    print('| boxes | iou_3d (ms) | giou_3d (ms) | per-pair loop baseline (ms) | speed-up |')
    print('|---|---|---|---|---|')
    for name, make in (('room (sparse overlaps)', scene_boxes), ('dense (most overlap)', dense_boxes)):
        a, b = make(rng, args.n), make(rng, args.n)
        t_iou = median_seconds(lambda: iou_3d(a, b), args.repeats)
        t_giou = median_seconds(lambda: giou_3d(a, b), args.repeats)
        t_loop = median_seconds(lambda: loop_baseline(a, b), max(3, args.repeats // 2))
        assert np.allclose(iou_3d(a, b), loop_baseline(a, b))
        print(f'| {name} | {t_iou * 1e3:.1f} | {t_giou * 1e3:.1f} | {t_loop * 1e3:.0f} | '
              f'{t_loop / t_iou:.0f}x |')


if __name__ == '__main__':
    main()
