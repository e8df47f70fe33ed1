"""Benchmark: per-frame detector latency, one core.

depth_clusters at 320x240 and 640x480 on rendered RGB-D frames of 3 rooms (noise on), at
its default input resolution (stride 2) and, as the baseline measured in the same run, at
full resolution (stride 1); the ground_truth backend (noise model only); and CuTR (RGB and
RGB-D variants, random weights: the latency does not depend on them) on fewer frames.

    ros_ws/env.sh python bench/bench_detector.py [--frames 10]
"""
import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'          # one core, before numpy loads

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from rfm_core.detection import make_detector  # noqa: E402
from rfm_core.detection.base import DetectorInput  # noqa: E402
from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: E402


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
        for seed in (200, 201, 202):
            cap = Capture(CaptureConfig(seed=seed, width=w, height=h, frames=args.frames, fps=2,
                                        room_style='textured' if seed % 2 else 'plain'))
            frames += [(cap, f) for f in cap.frames()]
        inputs = [DetectorInput(f.stamp_ns, 'cam', cap.intrinsics, f.ground_truth.gravity_cam,
                                f.render.rgb, f.render.depth) for cap, f in frames]
        for stride in (2, 1):
            det = make_detector('depth_clusters', stride=stride)
            results[(f'depth_clusters (stride {stride})', w)] = median_ms(det.detect, inputs)
        gt = make_detector('ground_truth', preset='rgbd')
        results[('ground_truth:rgbd', w)] = median_ms(gt.perturb, [f.ground_truth for _, f in frames])
        if args.cutr:
            import torch  # noqa: PLC0415

            from rfm_core.detection.cutr import CutrConfig, CutrDetector  # noqa: PLC0415
            from rfm_core.detection.cutr_model import CubifyTransformer  # noqa: PLC0415
            torch.set_num_threads(1)
            for rgbd in (False, True):
                det = CutrDetector(CutrConfig(), model=CubifyTransformer(rgbd=rgbd).eval())
                name = f'cutr ({"RGB-D" if rgbd else "RGB"}, CPU, random weights)'
                results[(name, w)] = median_ms(det.detect, inputs[:args.cutr_frames])
    for name in dict.fromkeys(k for k, _ in results):
        print(f'| {name} | {results[(name, 320)]:.1f} | {results[(name, 640)]:.1f} |')
    ratio = results[('depth_clusters (stride 1)', 320)] / results[('depth_clusters (stride 2)', 320)]
    print(f'\nstride 2 is {ratio:.1f}x faster than full resolution at 320x240 (same run)')


if __name__ == '__main__':
    np.seterr(all='ignore')
    main()
