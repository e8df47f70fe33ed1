"""Benchmark: relative poses between frames of a bag, from the boxes (with the floor and walls)
and refined on the frames' depth points (``matching.point_refine``), against the truth.

Every third frame of the bag is paired with the frame ``gap`` frames later; the depth
detector runs on both as the detector node would (gravity from the IMU), the learned matcher
matches them, and the relative pose is estimated once with ``point_refine`` off and once on.
Reported per gap: the pairs that verified, the yaw error (p50 / p90, deg) and the
translation error (p50 / p75 / p90, cm), and the median cost of the refinement.

    ros_ws/env.sh python bench/point_pairs.py BAG [BAG ...] [--gaps 3 6 10 15]
"""
import argparse
import time

import numpy as np

from rfm_core.detection import make_detector
from rfm_core.evaluation.detection_bags import detector_inputs
from rfm_core.evaluation.report import read_ground_truth
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.factory import make_matcher
from rfm_core.matching.relative_pose import estimate_relative_pose, with_surfaces
from rfm_core.sim.capture import aligned_from_map


def pairs(bag: str, gaps) -> tuple[dict, list]:
    truth = read_ground_truth(bag).camera_poses
    detector, matcher = make_detector('depth_clusters'), make_matcher('learned')
    frames = []
    for frame, inp in detector_inputs(bag):
        if inp is not None and frame['stamp_ns'] in truth:
            pose = truth[frame['stamp_ns']]
            frames.append((detector.detect(inp), aligned_from_map(pose[:3, :3], pose[:3, 3])))
    configs = {'boxes, floor, walls': MatchingConfig(point_refine=False), '+ depth points': MatchingConfig()}
    errors, cost = {name: {g: [] for g in gaps} for name in configs}, []
    for gap in gaps:
        for i in range(0, len(frames) - gap, 3):
            (a, ta), (b, tb) = frames[i], frames[i + gap]
            matches = matcher.match(b, a)
            t_a_b = ta @ tb.inverse()
            for name, cfg in configs.items():
                rel = estimate_relative_pose(b.boxes, a.boxes, matches, cfg)
                if rel is None:
                    continue
                rel.swap_index_order()
                start = time.perf_counter()
                with_surfaces(rel, a, b, cfg)
                if cfg.point_refine:
                    cost.append(time.perf_counter() - start)
                errors[name][gap].append((np.degrees(rel.pose.angle_to(t_a_b)),
                                          100 * np.linalg.norm(np.asarray(rel.pose.t) - t_a_b.t)))
    return errors, cost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('bags', nargs='+')
    parser.add_argument('--gaps', type=int, nargs='+', default=[3, 6, 10, 15])
    args = parser.parse_args()
    print('| bag | gap (frames) | relative pose | pairs | yaw p50 / p90 (deg) | translation p50 / p75 / p90 (cm) |')
    print('|---|---|---|---|---|---|')
    for bag in args.bags:
        errors, cost = pairs(bag, args.gaps)
        for gap in args.gaps:
            for name, by_gap in errors.items():
                e = np.array(by_gap[gap]).reshape(-1, 2)
                if not len(e):
                    continue
                yaw, t = np.percentile(e[:, 0], [50, 90]), np.percentile(e[:, 1], [50, 75, 90])
                print(f'| {bag} | {gap} | {name} | {len(e)} | {yaw[0]:.2f} / {yaw[1]:.2f} | '
                      f'{t[0]:.1f} / {t[1]:.1f} / {t[2]:.1f} |')
        print(f'| {bag} | | refinement cost, median | {len(cost)} | {1e3 * np.median(cost):.1f} ms | |')


if __name__ == '__main__':
    main()
