"""How well does checking a relocalized pose against the whole map tell right poses from
wrong ones? (#20; `relocalization.min_explained`)

    ros_ws/env.sh python bench/reloc_verification.py [--first-seed 40] [--scenes 8]

For each stream scene of the realistic world (`rfm eval`'s suite, tuning seeds by default;
sparse scenes skipped): map the capture with ``depth_clusters`` in one process, then
relocalize every frame of a second walk through the same room (another trajectory seed)
with the whole-map check off, and record for each relocalized frame whether it is wrong
(> 5 deg or > 25 cm from the truth, after the map's alignment to the world) and how many of
its detections the pose explains. Prints, for each threshold, the right and wrong poses it
keeps (``min(threshold, detections)``: a query with fewer detections must explain all);
then, on top of the default 4, what two more rules keep: the pose explains more than the
best distinct alternative (``Relocalization.runner_up``), and half of the query's detections.
"""
from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--first-seed', type=int, default=40)
    parser.add_argument('--scenes', type=int, default=8)
    args = parser.parse_args()
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import detections_for, run_capture  # noqa: PLC0415
    from rfm_core.evaluation.suite import eval_configs  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415
    torch.set_num_threads(1)
    rows = []                                           # (wrong, explained, detections)
    for config in eval_configs(args.scenes, args.first_seed):
        if config.capture == 'sparse':
            continue
        mapped = run_capture(config, 'depth_clusters', noise_seed=3)
        mapper = mapped.mapper
        mapper.config = replace(mapper.config, relocalization=replace(mapper.config.relocalization, min_explained=0))
        mapper.mode = 'localization'
        world = map_to_truth(mapper.camera_poses(), mapped.truth).matrix()
        detect = detections_for('depth_clusters', 11)
        before = len(rows)
        for frame in Capture(replace(config, trajectory_seed=1)).frames():
            obs = detect(frame)
            reloc = mapper.relocalize(obs)
            if reloc is None:
                continue
            est, true = world @ reloc.camera_to_map(obs), frame.pose_matrix
            turn = np.degrees(np.arccos(np.clip((np.trace(est[:3, :3].T @ true[:3, :3]) - 1) / 2, -1, 1)))
            rows.append((turn > 5 or np.linalg.norm(est[:3, 3] - true[:3, 3]) > 0.25, reloc.explained, len(obs),
                         reloc.runner_up))
        wrong = sum(r[0] for r in rows[before:])
        print(f'{config.seed} {config.capture}: {len(rows) - before} relocalized, {wrong} wrong', flush=True)
    wrong, count, n, runner_up = (np.array([r[i] for r in rows]) for i in range(4))
    wrong = wrong.astype(bool)
    print(f'\n| min_explained | right poses kept | wrong poses kept | wrong share |\n|---|---|---|---|')
    for threshold in (0, 2, 3, 4, 5):
        keep = count >= np.minimum(threshold, n)
        print(f'| {threshold} | {np.sum(keep & ~wrong)} of {np.sum(~wrong)} | {np.sum(keep & wrong)} of {np.sum(wrong)} '
              f'| {100 * np.sum(keep & wrong) / max(np.sum(keep), 1):.0f}% |')
    print('\nWith the default min_explained (4), further rules:\n\n| rule | right poses kept | wrong poses kept | '
          'wrong share |\n|---|---|---|---|')
    base = count >= np.minimum(4, n)
    rules = {'none': base, 'more than the best distinct alternative pose': base & (count > runner_up),
             'half of the detections': base & (count >= 0.5 * n),
             'both': base & (count > runner_up) & (count >= 0.5 * n)}
    for name, keep in rules.items():
        print(f'| {name} | {np.sum(keep & ~wrong)} | {np.sum(keep & wrong)} '
              f'| {100 * np.sum(keep & wrong) / max(np.sum(keep), 1):.0f}% |')
    return 0

if __name__ == '__main__':
    raise SystemExit(main())
