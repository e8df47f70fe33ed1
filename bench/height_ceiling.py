"""How much of a run's keyframe ATE a measured camera height could remove (an oracle ceiling).

Loads the map each `rfm run` output folder saved, re-solves its keyframe poses from its
edges twice with the mapper's averaging (all keyframes and edges, one full solve): as
measured, and with every box edge's height (z of T_source_target, the camera-height
difference in the gravity-aligned frames) replaced by the true one from the bag's
``/ground_truth/camera_pose``. The gap between the two is what a per-frame height (the
detector's floor fit) could at best give the edges' vertical part; yaw and horizontal
translation stay as measured.

    ros_ws/env.sh python bench/height_ceiling.py --bag bags/demo OUT1 [OUT2 ...]
"""
import argparse

import numpy as np

from rfm_core.evaluation.report import read_ground_truth
from rfm_core.evaluation.trajectory import trajectory_errors
from rfm_core.geometry import Pose4
from rfm_core.mapping.averaging import IncrementalAverager
from rfm_core.mapping.map_io import load_map
from rfm_core.mapping.mapper import Mapper, camera_to_map


def resolve(mapper: Mapper, truth: dict, oracle: bool) -> dict:
    """{stamp: camera-to-map} of the keyframes re-solved from the map's edges."""
    averager, edges = mapper.averager, mapper.averager.edges
    ids = averager.ids
    solver = IncrementalAverager(mapper.config.averaging)
    for k in ids:
        solver.add_keyframe(k)
    for i in range(len(edges)):
        s, t = ids[edges.src[i]], ids[edges.dst[i]]
        trans = np.array(edges.trans[i])
        if oracle and not edges.yaw_only[i] and s in truth and t in truth:
            trans[2] = truth[t][2, 3] - truth[s][2, 3]
        solver.add_edge(s, t, Pose4(edges.yaw[i], trans), edges.weight[i], yaw_only=bool(edges.yaw_only[i]))
    solver.update(force_full=True)
    return {mapper.keyframes[k].stamp_ns: camera_to_map(p, mapper.keyframes[k]) for k, p in solver.poses.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', required=True, help='the bag the runs replayed (with ground truth)')
    parser.add_argument('runs', nargs='+', help='rfm run output folders (each with map.rfm)')
    args = parser.parse_args()
    gt = read_ground_truth(args.bag).camera_poses
    print('| run | keyframes | as measured: ARE (deg) / ATE (cm) | true heights: ARE (deg) / ATE (cm) |')
    print('|---|---|---|---|')
    for run in args.runs:
        mapper = Mapper()
        load_map(mapper, f'{run}/map.rfm')
        truth = {k: gt[f.stamp_ns] for k, f in mapper.keyframes.items() if f.stamp_ns in gt}
        by_stamp = {mapper.keyframes[k].stamp_ns: pose for k, pose in truth.items()}
        cells = []
        for oracle in (False, True):
            est = resolve(mapper, truth, oracle)
            err = trajectory_errors(est, by_stamp)
            cells.append(f"{err['ARE_median']:.2f} / {100 * err['ATE_median']:.1f}")
        print(f'| {run} | {len(truth)} | {cells[0]} | {cells[1]} |')


if __name__ == '__main__':
    main()
