"""Object tracks: the cost of rebuilding a map's tracks (`rfm_core.mapping.tracks.build_tracks`).

The mapper rebuilds every track whenever poses change (the node rate-limits it by
`map_max_cpu_share`), so this is what bounds how fresh the published map is. Maps come
from the evaluation pipeline with depth_clusters (the detector whose fragments make the
most tracks): one handheld walk and two sparse captures of 100 frames. ``--baseline REV``
also times `tracks.py` as of a git revision in the same run, alternating, and says whether
both build the same tracks (or how they differ).

    ros_ws/env.sh python bench/bench_tracks.py [--repeats 5] [--baseline REV]
"""
import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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


def module_at(revision: str):
    """rfm_core.mapping.tracks as of a git revision."""
    root = Path(__file__).resolve().parents[1]
    source = subprocess.run(['git', 'show', f'{revision}:src/rfm_core/rfm_core/mapping/tracks.py'], cwd=root,
                            check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / 'tracks_baseline.py'
    path.write_text(source)
    spec = importlib.util.spec_from_file_location('tracks_baseline', path)
    module = importlib.util.module_from_spec(spec)
    sys.modules['tracks_baseline'] = module
    spec.loader.exec_module(module)
    return module


def compare(a, b) -> str:
    """'same', or how the two track lists differ: in grouping, or in representatives."""
    if len(a) != len(b) or any(x.track_id != y.track_id or not np.array_equal(x.observations, y.observations)
                               for x, y in zip(a, b)):
        return f'grouped differently ({len(a)} vs {len(b)} tracks)'
    other = sum(not np.allclose(x.box, y.box) or abs(x.score - y.score) > 1e-9 for x, y in zip(a, b))
    return f'{other} other representatives' if other else 'same'


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--baseline', help='git revision whose tracks.py to time alongside')
    args = parser.parse_args()
    from rfm_core.mapping import tracks  # noqa: PLC0415

    baseline = module_at(args.baseline) if args.baseline else None
    print('| map | keyframes | observations | tracks | build_tracks (median, s) |'
          + (f' {args.baseline} (s) | ratio | tracks |' if baseline else ''))
    print('|---|---|---|---|---|' + ('---|---|---|' if baseline else ''))
    for name, keyframes, poses, matches, config in maps():
        now, before = [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            result = tracks.build_tracks(keyframes, poses, matches, config)
            now.append(time.perf_counter() - t)
            if baseline:
                t = time.perf_counter()
                reference = baseline.build_tracks(keyframes, poses, matches, config)
                before.append(time.perf_counter() - t)
        n_obs = sum(len(keyframes[k]) for k in poses)
        row = f'| {name} | {len(poses)} | {n_obs} | {len(result)} | {np.median(now):.3f} |'
        if baseline:
            row += (f' {np.median(before):.3f} | {np.median(now) / np.median(before):.2f} | '
                    f'{compare(result, reference)} |')
        print(row)


if __name__ == '__main__':
    main()
