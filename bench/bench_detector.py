"""Benchmark: per-frame detector latency, one core.

depth_clusters at 320x240 and 640x480 on rendered RGB-D frames of 3 rooms of the realistic
world (furniture made of parts, clutter; the realsense sensor model in one), with its
learned box refiner (the default) and, as baselines measured in the same run, with the
heuristic boxes (``box_refiner=''``) and at full resolution (stride 1); the ground_truth
backend (noise model only); and CuTR (RGB and RGB-D variants, random weights: the latency
does not depend on them) on fewer frames.

    ros_ws/env.sh python bench/bench_detector.py [--frames 10]
"""
import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'          # one core, before numpy loads

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from rfm_core.detection import make_detector  # noqa: E402
from rfm_core.evaluation.suite import eval_configs  # noqa: E402
from rfm_core.sim.capture import Capture  # noqa: E402

torch.set_num_threads(1)


def median_ms(fn, items):
    times = []
    for item in items:
        start = time.perf_counter()
        fn(item)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--frames', type=int, default=10, help='frames per room')
    parser.add_argument('--no-cutr', dest='cutr', action='store_false', help='skip CuTR')
    parser.add_argument('--cutr-frames', type=int, default=3)
    args = parser.parse_args()
    print(f'# detector latency per frame, median over 3 rooms x {args.frames} frames, one core')
    print('| backend | 320x240 (ms) | 640x480 (ms) |')
    print('|---|---|---|')
    results = {}
    for w, h in ((320, 240), (640, 480)):
        frames = []
        for config in eval_configs(3, first_seed=200):       # tuning seeds; the third: realsense
            config = replace(config, width=w, height=h, hfov_deg=70.0)
            frames += list(Capture(config).frames(np.linspace(0, config.frames - 1, args.frames).round()))
        inputs = [f.detector_input() for f in frames]
        variants = {'depth_clusters (box refiner, stride 2)': {},
                    "depth_clusters (heuristic boxes: box_refiner='', stride 2)": {'box_refiner': ''},
                    'depth_clusters (box refiner, stride 1)': {'stride': 1}}
        for name, options in variants.items():
            det = make_detector('depth_clusters', **options)
            results[(name, w)] = median_ms(det.detect, inputs)
        gt = make_detector('ground_truth', preset='rgbd')
        results[('ground_truth:rgbd', w)] = median_ms(gt.perturb, [f.ground_truth for f in frames])
        if args.cutr:
            from rfm_core.detection.cutr import CutrConfig, CutrDetector  # noqa: PLC0415
            from rfm_core.detection.cutr_model import CubifyTransformer  # noqa: PLC0415
            for rgbd in (False, True):
                det = CutrDetector(CutrConfig(), model=CubifyTransformer(rgbd=rgbd).eval())
                name = f'cutr ({"RGB-D" if rgbd else "RGB"}, CPU, random weights)'
                results[(name, w)] = median_ms(det.detect, inputs[:args.cutr_frames])
    for name in dict.fromkeys(k for k, _ in results):
        print(f'| {name} | {results[(name, 320)]:.1f} | {results[(name, 640)]:.1f} |')
    base = results[('depth_clusters (box refiner, stride 2)', 320)]
    heuristic = results[("depth_clusters (heuristic boxes: box_refiner='', stride 2)", 320)]
    full = results[('depth_clusters (box refiner, stride 1)', 320)]
    print(f'\nat 320x240 (same run): the box refiner costs {base / heuristic:.2f}x the heuristic boxes; '
          f'stride 2 is {full / base:.1f}x faster than full resolution')


if __name__ == '__main__':
    np.seterr(all='ignore')
    main()
