"""Object tracks: the cost of rebuilding a map's tracks (`rfm_core.mapping.tracks.build_tracks`).

The mapper rebuilds every track whenever poses change (the node rate-limits it by
`map_max_cpu_share`), so this is what bounds how fresh the published map is. Maps come
from the evaluation pipeline with depth_clusters (the detector whose fragments make the
most tracks): one handheld walk and two sparse captures of 100 frames.

    ros_ws/env.sh python bench/bench_tracks.py [--repeats 5]
"""
import argparse
import time

import numpy as np

SCENES = ((11, 'handheld'), (11, 'sparse'), (12, 'sparse'))


def maps():
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import run_capture  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import CaptureConfig  # noqa: PLC0415

    torch.set_num_threads(1)
    for seed, capture in SCENES:
        config = CaptureConfig(seed=seed, room_style='textured', capture=capture, frames=100, fps=10)
        m = run_capture(config, 'depth_clusters', matcher=make_matcher('learned')).mapper
        matches = [(e.source, int(a), e.target, int(b)) for e in m.active_edges() for a, b in e.inliers]
        yield f'{seed} {capture}', m.keyframes, m.poses, matches, m.config.tracks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=5)
    args = parser.parse_args()
    from rfm_core.mapping import tracks  # noqa: PLC0415

    print('| map | keyframes | observations | tracks | build_tracks (median, s) |')
    print('|---|---|---|---|---|')
    for name, keyframes, poses, matches, config in maps():
        now = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            result = tracks.build_tracks(keyframes, poses, matches, config)
            now.append(time.perf_counter() - t)
        n_obs = sum(len(keyframes[k]) for k in poses)
        print(f'| {name} | {len(poses)} | {n_obs} | {len(result)} | {np.median(now):.3f} |')


if __name__ == '__main__':
    main()
