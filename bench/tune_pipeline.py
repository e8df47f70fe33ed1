"""Ablations on tuning scenes: the in-process pipeline (every frame detected, the simulator's
gravity and gyroscope) over a range of tuning seeds, with view-graph settings overridden.

Never point it at evaluation seeds (5000+): it is for choosing settings, which are then
measured once through the node graph (``rfm eval``). Seeds alternate plain (even) and
textured (odd) rooms; 100 frames at 10 fps.

    ros_ws/env.sh python bench/tune_pipeline.py --seeds 52 76 [--capture sparse] \
        [--set min_overlap=0.3 max_motion_edge_s=0] [--jobs 2]

Prints one line per scene and the summary: frames localized (all frames) and keyframes
registered, ARE/ATE medians over scenes, scenes over 3 deg ARE, AP25/AR25 (mean), objects
mapped per object in the room (median), keyframes and matching seconds (mean).
"""
import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np


def scene(args) -> dict:
    seed, capture, overrides, detector = args
    import torch
    torch.set_num_threads(1)
    from rfm_core.evaluation.pipeline import run_capture
    from rfm_core.matching.factory import make_matcher
    from rfm_core.matching.view_graph import KeyframeConfig
    from rfm_core.sim.capture import CaptureConfig
    if seed >= 5000:
        raise SystemExit('tune_pipeline: seeds 5000+ are evaluation seeds; tune on 0-4999')
    style = 'plain' if seed % 2 == 0 else 'textured'
    start = time.perf_counter()
    r = run_capture(CaptureConfig(seed=seed, room_style=style, capture=capture, frames=100, fps=10), detector,
                    matcher=make_matcher('learned'), keyframe_config=KeyframeConfig(**overrides))
    loc, m = r.localization, r.mapping
    return dict(seed=seed, style=style, reg=loc['registered'], kreg=loc['keyframe_registered'],
                are=loc['ARE_median'], ate=loc['ATE_median'], ap25=m['AP25'], ar25=m['AR25'], obj=m['objects'],
                gt=m['ground_truth'], kf=r.keyframes, s=time.perf_counter() - start, match=r.seconds['match'])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--seeds', type=int, nargs=2, default=[52, 76], metavar=('FIRST', 'END'))
    parser.add_argument('--capture', default='handheld', choices=('handheld', 'sparse', 'orbit'))
    parser.add_argument('--detector', default='depth_clusters')
    parser.add_argument('--set', nargs='*', default=[], metavar='FIELD=JSON',
                        help='KeyframeConfig overrides, e.g. min_overlap=0.6')
    parser.add_argument('--jobs', type=int, default=2)
    args = parser.parse_args()
    overrides = {k: json.loads(v) for k, v in (item.split('=', 1) for item in args.set)}
    work = [(s, args.capture, overrides, args.detector) for s in range(*args.seeds)]
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(scene, work))
    for r in rows:
        print(f"{r['seed']:4d} {r['style']:8s} localized {100 * r['reg']:5.1f}% keyframes {100 * r['kreg']:5.1f}% "
              f"ARE {r['are']:6.2f} ATE {100 * r['ate']:6.1f} cm AP25 {r['ap25']:.3f} objects {r['obj']:3d}/{r['gt']:2d} "
              f"keyframes {r['kf']:3d} ({r['s']:.0f} s)")

    def col(k):
        return np.array([r[k] for r in rows], float)
    print(f"{args.capture} seeds {args.seeds[0]}-{args.seeds[1] - 1} {overrides or 'defaults'}: "
          f"localized {100 * col('reg').mean():.1f}%, keyframes {100 * col('kreg').mean():.1f}%, "
          f"ARE {np.nanmedian(col('are')):.2f} deg, ATE {100 * np.nanmedian(col('ate')):.1f} cm, "
          f"{int((col('are') > 3).sum())} scenes > 3 deg, AP25 {col('ap25').mean():.3f}, AR25 {col('ar25').mean():.3f}, "
          f"objects/room {np.median(col('obj') / np.maximum(col('gt'), 1)):.1f}, keyframes {col('kf').mean():.1f}, "
          f"matching {col('match').mean():.1f} s")


if __name__ == '__main__':
    main()
