"""Are wrong relocalizations wrong against the map, or is the map wrong? (#20)

    ros_ws/env.sh rfm eval-reloc --scenes 10 --first-seed 5100 --jobs 2 --work W
    ros_ws/env.sh python bench/reloc_local_error.py W [--nearest 5]

`rfm eval-reloc` scores each relocalized query frame in the world frame through the mapping
run's one 4-DoF alignment of all its keyframes to the truth, so a map that bends or drifts
makes right relocalizations count as wrong. Here each relocalized frame is also scored
through a *local* alignment: of the map's registered keyframes, the ``--nearest`` whose true
camera centres lie nearest the query's true centre, aligned to the truth alone. Per room and
over all: relocalized frames, wrong (> 5 deg or > 25 cm) in the world frame and locally,
and the median errors both ways.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _errors(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(deg, m) between two 4x4 camera poses."""
    rel = truth[:3, :3].T @ est[:3, :3]
    deg = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
    return deg, float(np.linalg.norm(est[:3, 3] - truth[:3, 3]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path, help='an rfm eval-reloc --work folder')
    parser.add_argument('--nearest', type=int, default=5, help='keyframes in the local alignment')
    args = parser.parse_args()
    from rfm_core.evaluation.report import read_ground_truth  # noqa: PLC0415
    from rfm_core.evaluation.suite import camera_poses_of_run  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth  # noqa: PLC0415
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415

    print('| room | relocalized | wrong (world) | wrong (local) | ARE / ATE median, world | ARE / ATE median, local |')
    print('|---|---|---|---|---|---|')
    pooled = []
    for scene in sorted(p for p in args.work.iterdir() if (p / 'query_run' / 'outputs.mcap').exists()):
        mapper = Mapper()
        load_map(mapper, scene / 'map_run' / 'map.rfm')
        map_truth = read_ground_truth(scene / 'map_bag').camera_poses
        keyframes = {mapper.keyframes[k].stamp_ns: m for k, m in mapper.camera_poses().items()
                     if mapper.keyframes[k].stamp_ns in map_truth}
        if len(keyframes) < 2:
            continue
        stamps = np.array(sorted(keyframes))
        centres = np.array([map_truth[s][:3, 3] for s in stamps])
        world = map_to_truth(keyframes, map_truth).matrix()
        truth = read_ground_truth(scene / 'query_bag').camera_poses
        rows = []
        for stamp, pose in camera_poses_of_run(scene / 'query_run').items():
            if stamp not in truth:
                continue
            near = stamps[np.argsort(np.linalg.norm(centres - truth[stamp][:3, 3], axis=1))[:args.nearest]]
            local = map_to_truth({s: keyframes[s] for s in near}, {s: map_truth[s] for s in near}).matrix()
            rows.append((*_errors(world @ pose, truth[stamp]), *_errors(local @ pose, truth[stamp])))
        rows = np.array(rows, float).reshape(-1, 4)
        pooled.append(rows)
        wrong_w = (rows[:, 0] > 5) | (rows[:, 1] > 0.25)
        wrong_l = (rows[:, 2] > 5) | (rows[:, 3] > 0.25)
        med = np.median(rows, 0) if len(rows) else np.full(4, np.nan)
        print(f'| {scene.name} | {len(rows)} | {int(wrong_w.sum())} | {int(wrong_l.sum())} | {med[0]:.2f} / '
              f'{100 * med[1]:.1f} | {med[2]:.2f} / {100 * med[3]:.1f} |')
    rows = np.concatenate(pooled) if pooled else np.zeros((0, 4))
    wrong_w = (rows[:, 0] > 5) | (rows[:, 1] > 0.25)
    wrong_l = (rows[:, 2] > 5) | (rows[:, 3] > 0.25)
    med = np.median(rows, 0) if len(rows) else np.full(4, np.nan)
    print(f'| all | {len(rows)} | {int(wrong_w.sum())} ({100 * wrong_w.mean():.1f}%) | {int(wrong_l.sum())} '
          f'({100 * wrong_l.mean():.1f}%) | {med[0]:.2f} / {100 * med[1]:.1f} | {med[2]:.2f} / {100 * med[3]:.1f} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
