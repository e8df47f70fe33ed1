"""Per-frame accuracy of depth_clusters with and without its learned box refiner.

Frames spread over scenes of the realistic world (``rfm eval``'s default: furniture made of
parts, clutter, both sensor models), the simulator's true gravity; per-frame AP/AR at 3D IoU
0.15 / 0.25 (ground truth seen < 20% ignored), detections per frame and median latency.

    ros_ws/env.sh python bench/refiner_accuracy.py [--first-seed 5000] [--scenes 20] [--frames 8]

Variants: ``heuristic`` (box_refiner='': fitted boxes, calibrated score), ``fitted`` (the
refiner scores and suppresses, fitted boxes only), ``default`` (the same detections with the
refiner's predicted full boxes attached: they are what is scored), ``refined`` (its
predicted boxes published instead of the fitted ones, suppressed among themselves).
"""
import argparse
import time

import numpy as np
import torch

from rfm_core.detection import make_detector
from rfm_core.evaluation.detection import DetectionEvaluator
from rfm_core.evaluation.suite import WORLDS, eval_configs
from rfm_core.sim.capture import Capture

VARIANTS = {'heuristic': {'box_refiner': ''}, 'fitted': {'predicted_boxes': 'off'}, 'default': {},
            'refined': {'predicted_boxes': 'all'}}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--first-seed', type=int, default=5000)
    parser.add_argument('--scenes', type=int, default=20)
    parser.add_argument('--frames', type=int, default=8, help='frames per scene, spread over the capture')
    parser.add_argument('--world', choices=WORLDS, default='realistic')
    args = parser.parse_args()
    torch.set_num_threads(1)
    detectors = {k: make_detector('depth_clusters', **v) for k, v in VARIANTS.items()}
    evaluators = {k: DetectionEvaluator() for k in VARIANTS}
    latency = {k: [] for k in VARIANTS}
    counts = {k: [] for k in VARIANTS}
    visible = []
    for config in eval_configs(args.scenes, first_seed=args.first_seed, world=args.world):
        indices = np.linspace(0, config.frames - 1, args.frames).round().astype(int)
        for frame in Capture(config).frames(indices):
            visible.append(int(np.sum(frame.ground_truth.visibility >= 0.2)))
            for k, det in detectors.items():
                start = time.perf_counter()
                obs = det.detect(frame.detector_input())
                latency[k].append(time.perf_counter() - start)
                evaluators[k].add(obs, frame.ground_truth)
                counts[k].append(len(obs))
    print(f'# {len(visible)} frames of {args.scenes} {args.world} scenes from seed {args.first_seed}, '
          f'{np.mean(visible):.1f} objects visible per frame')
    print('| depth_clusters | AP15 | AP25 | AR25 | detections / frame | median ms |')
    print('|---|---|---|---|---|---|')
    for k in VARIANTS:
        s = evaluators[k].summary()
        print(f'| {k} | {s["AP15"]:.3f} | {s["AP25"]:.3f} | {s["AR25"]:.3f} | {np.mean(counts[k]):.1f} | '
              f'{1e3 * np.median(latency[k]):.0f} |')


if __name__ == '__main__':
    np.seterr(all='ignore')
    main()
