"""How well `depth_clusters` measures the camera's height above the floor (FrameDetections.camera_height).

    ros_ws/env.sh python bench/camera_height.py BAG [BAG ...] [--every 2]

Each bag must carry ``/ground_truth/camera_pose`` (the simulator's bags: the floor is z = 0).
Every n-th frame is detected as the node would (gravity from the IMU filter) and the
detector's height is compared with the true one: a constant bias per bag cancels in the
height differences the matcher uses, the spread around it does not.
"""
import argparse

import numpy as np

from rfm_core.detection.depth_clusters import DepthClustersDetector
from rfm_core.evaluation.detection_bags import detector_inputs
from rfm_core.evaluation.report import read_ground_truth


def heights(bag: str, every: int):
    """(frames detected, [measured - true height (m)] of the frames with a floor)."""
    truth = read_ground_truth(bag).camera_poses
    detector = DepthClustersDetector()
    errors, frames = [], 0
    for f, inp in detector_inputs(bag, every=every):
        if inp is None or f['stamp_ns'] not in truth:
            continue
        frames += 1
        obs = detector.detect(inp)
        if np.isfinite(obs.camera_height):
            errors.append(obs.camera_height - truth[f['stamp_ns']][2, 3])
    return frames, np.array(errors)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bags', nargs='+')
    parser.add_argument('--every', type=int, default=2, help='detect every n-th frame')
    args = parser.parse_args()
    print('| bag | frames with a floor | bias (cm) | spread around it: median / p90 (cm) | frames > 10 cm off |')
    print('|---|---|---|---|---|')
    for bag in args.bags:
        frames, err = heights(bag, args.every)
        if not len(err):
            print(f'| {bag} | 0 of {frames} | - | - | - |')
            continue
        bias = np.median(err)
        dev = np.abs(err - bias)
        print(f'| {bag} | {len(err)} of {frames} | {100 * bias:.1f} | {100 * np.median(dev):.2f} / '
              f'{100 * np.percentile(dev, 90):.2f} | {int(np.sum(dev > 0.1))} |')


if __name__ == '__main__':
    main()
