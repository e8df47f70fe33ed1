"""Tracking lost for seconds: does the map stay one component? (#20 item 3; mapper
`relocalization.recovery`)

    ros_ws/env.sh python bench/tracking_gap.py [--seeds 40 41 42 43 44 45 46] [--gap 5 8]

For each seed: a 15 s handheld walk (10 Hz, furniture made of parts) seen by
``depth_clusters`` in one process, with no frame between ``--gap`` seconds (the gyroscope
runs on), mapped with tracking recovery off and on. Prints the view graph's components, the
keyframes registered, the share of frames localized (before / after the gap) and the median
pose errors over all localized frames after a 4-DoF alignment, and each recovered edge's
error against the true relative pose.
"""
from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seeds', type=int, nargs='+', default=[40, 41, 42, 43, 44, 45, 46])
    parser.add_argument('--gap', type=float, nargs=2, default=(5.0, 8.0), metavar=('FROM_S', 'TO_S'))
    args = parser.parse_args()
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import detections_for  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import trajectory_errors  # noqa: PLC0415
    from rfm_core.geometry import gravity_aligned_rotation  # noqa: PLC0415
    from rfm_core.mapping.mapper import MapperConfig  # noqa: PLC0415
    from rfm_core.session import Session  # noqa: PLC0415
    from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: PLC0415
    torch.set_num_threads(1)

    def edge_error(mapper, edge, truth):
        a, b = mapper.keyframes[edge.source], mapper.keyframes[edge.target]
        ra, rb = gravity_aligned_rotation(a.gravity_cam), gravity_aligned_rotation(b.gravity_cam)
        measured = np.eye(4)
        measured[:3, :3], measured[:3, 3] = ra.T @ edge.pose.rotation @ rb, ra.T @ edge.pose.t
        true = np.linalg.inv(truth[a.stamp_ns]) @ truth[b.stamp_ns]
        cos = (np.trace(measured[:3, :3].T @ true[:3, :3]) - 1) / 2
        return np.degrees(np.arccos(np.clip(cos, -1, 1))), np.linalg.norm(measured[:3, 3] - true[:3, 3])

    print('| seed | recovery | components | keyframes registered | localized before / after the gap | '
          'ARE (deg) | ATE (cm) | recovered edges (error) |')
    print('|---|---|---|---|---|---|---|---|')
    for seed in args.seeds:
        detect = detections_for('depth_clusters', noise_seed=2)
        observations, truth, after_gap = [], {}, []
        for frame in Capture(CaptureConfig(seed=seed, frames=150, fps=10, furniture='parts')).frames():
            t = frame.index / 10
            if args.gap[0] <= t < args.gap[1]:
                continue
            obs = detect(frame)
            obs.imu_rotation, obs.imu_epoch = frame.rotation, 1
            truth[obs.stamp_ns] = frame.pose_matrix
            observations.append(obs)
            if t >= args.gap[1]:
                after_gap.append(obs.stamp_ns)
        for recovery in (False, True):
            config = MapperConfig()
            session = Session(replace(config, relocalization=replace(config.relocalization, recovery=recovery)))
            for obs in observations:
                session.step(obs)
            session.finish()
            mapper = session.mapper
            poses = mapper.frame_poses()
            errors = trajectory_errors(poses, truth, align='4dof')
            before = [s for s in truth if s not in after_gap]
            share = (f'{100 * np.mean([s in poses for s in before]):.0f}% / '
                     f'{100 * np.mean([s in poses for s in after_gap]):.0f}%')
            edges = ', '.join(f'{a:.1f} deg {100 * d:.0f} cm'
                              for a, d in (edge_error(mapper, e, truth) for e in mapper.recovered)) or '-'
            print(f'| {seed} | {"on" if recovery else "off"} | {mapper.num_components()} | '
                  f'{len(mapper.poses)} / {len(mapper.keyframes)} | {share} | {errors["ARE_median"]:.2f} | '
                  f'{100 * errors["ATE_median"]:.1f} | {edges} |', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
