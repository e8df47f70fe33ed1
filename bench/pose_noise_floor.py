"""Accuracy floor of relative poses under a ground_truth noise preset (#5's pose target).

On the pairs `rfm eval-matching` scores (seeds 2000-2019, 12 frames at 2 Hz, pairs 2
frames apart sharing >= 3 visible objects, noise seed 2), fit the 4-DoF relative pose
from the TRUE object correspondences with the preset's exact per-object centre noise as
inverse-variance weights (the maximum-likelihood fit for Gaussian centre noise). Corners
add nothing beyond centre, size and yaw, of which they are functions; box yaws (noise
``yaw_sigma_deg`` per box, so sqrt(2) x that per matched pair) add little next to the
centres' spread. Also printed: the translation error when even the true yaw is given (a
bound no estimator can beat).

    ros_ws/env.sh python bench/pose_noise_floor.py [--preset rgbd]
"""
import argparse

import numpy as np

from rfm_core.detection.ground_truth import PRESETS
from rfm_core.geometry import kabsch_4dof, wrap_angle
from rfm_core.training.matcher import labelled_pairs, scene_configs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--preset', default='rgbd', choices=sorted(PRESETS))
    parser.add_argument('--scenes', type=int, default=20)
    parser.add_argument('--jobs', type=int, default=2)
    args = parser.parse_args()
    spec = f'ground_truth:{args.preset}'
    noise = PRESETS[args.preset]
    pairs = labelled_pairs(scene_configs(range(2000, 2000 + args.scenes), frames=12), [spec],
                           noise_seeds=(2,), gaps=(2,), min_shared=3, visible=True, jobs=args.jobs)[spec]
    yaw_err, t_err, t_err_true_yaw, shared = [], [], [], []
    for a, b in pairs:
        oa, ob = a.observations, b.observations
        common = sorted(set(oa.object_ids[oa.object_ids > 0]) & set(ob.object_ids[ob.object_ids > 0]))
        if len(common) < 2:
            continue
        ia = np.array([np.flatnonzero(oa.object_ids == i)[0] for i in common])
        ib = np.array([np.flatnonzero(ob.object_ids == i)[0] for i in common])
        ca, cb = oa.boxes[ia, :3], ob.boxes[ib, :3]
        sigma = [noise.center_sigma_m + noise.center_sigma_per_m * np.linalg.norm(c, axis=1) for c in (ca, cb)]
        w = 1.0 / (sigma[0] ** 2 + sigma[1] ** 2)
        truth = b.aligned_from_map @ a.aligned_from_map.inverse()          # T_b_a
        fit = kabsch_4dof(ca, cb, w)
        yaw_err.append(np.degrees(abs(wrap_angle(fit.yaw - truth.yaw))))
        t_err.append(np.linalg.norm(fit.t - truth.t))
        t = (w[:, None] * (cb - ca @ truth.rotation.T)).sum(0) / w.sum()
        t_err_true_yaw.append(np.linalg.norm(t - truth.t))
        shared.append(len(common))
    print(f'{spec}: {len(t_err)} pairs, median {np.median(shared):.0f} shared objects')
    print('| estimator | median yaw (deg) | median translation (cm) |\n|---|---|---|')
    print(f'| true matches, exact weights (ML on centres) | {np.median(yaw_err):.2f} | {100 * np.median(t_err):.1f} |')
    print(f'| ... and the true yaw given | 0 | {100 * np.median(t_err_true_yaw):.1f} |')


if __name__ == '__main__':
    main()
