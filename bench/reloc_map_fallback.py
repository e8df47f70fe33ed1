"""Relocalization against the map's objects when no keyframe places the query (#20 item 1;
mapper `relocalization.map_fallback`).

    ros_ws/env.sh python bench/reloc_map_fallback.py [--first-seed 40] [--scenes 12]

For each stream scene of the realistic world (tuning seeds by default; sparse scenes
skipped): map the capture with ``depth_clusters`` in one process, then relocalize every
frame of a second walk through the same room (2 Hz, another trajectory seed) with the
fallback off and on. Prints per scene and overall the share of query frames relocalized and
the share of those off by > 5 deg or > 25 cm.
"""
from __future__ import annotations

import argparse
from dataclasses import replace


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--first-seed', type=int, default=40)
    parser.add_argument('--scenes', type=int, default=12)
    args = parser.parse_args()
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import relocalize_capture, run_capture  # noqa: PLC0415
    from rfm_core.evaluation.suite import eval_configs  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415
    torch.set_num_threads(1)
    totals = {False: [0, 0.0, 0.0], True: [0, 0.0, 0.0]}        # frames, relocalized, wrong
    for config in eval_configs(args.scenes, args.first_seed):
        if config.capture == 'sparse':
            continue
        mapped = run_capture(config, 'depth_clusters', noise_seed=3)
        mapper = mapped.mapper
        mapper.mode = 'localization'
        world = map_to_truth(mapper.camera_poses(), mapped.truth)
        cells = []
        for fallback in (False, True):
            mapper.config = replace(mapper.config,
                                    relocalization=replace(mapper.config.relocalization, map_fallback=fallback))
            second = Capture(replace(config, frames=40, fps=2.0, capture='handheld', trajectory_seed=1))
            errors = relocalize_capture(mapper, world, second, 'depth_clusters', noise_seed=11)
            n, share, wrong = 40, errors['registered'], errors.get('wrong', 0.0)
            totals[fallback][0] += n
            totals[fallback][1] += share * n
            totals[fallback][2] += wrong * share * n
            cells.append(f'{100 * share:.0f}% relocalized, {100 * wrong:.0f}% wrong')
        print(f'{config.seed} {config.capture}: off {cells[0]} | on {cells[1]}', flush=True)
    for fallback, (n, relocalized, wrong) in totals.items():
        print(f'fallback {"on" if fallback else "off"}: relocalized {100 * relocalized / max(n, 1):.1f}%, '
              f'wrong {100 * wrong / max(relocalized, 1e-9):.1f}% of them')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
