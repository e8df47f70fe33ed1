"""Why do views of a sparse capture stay unregistered? (#15, #18: sparse captures register
59% of their views through the graph while 96% of them see two objects; an ablation
in-process, the product is `rfm run`)

    ros_ws/env.sh python bench/unregistered_views.py SEED [SEED ...] [--first-seed 40]

Each SEED names a scene of `rfm eval`'s suite (``eval_configs``; tuning seeds 40-79, never
the held-out 5100-5119 for choosing anything). Its capture is detected with
``depth_clusters`` and mapped by :class:`rfm_core.session.Session`; each detection is
associated with the room's object it overlaps best (IoU3D >= 0.2 with the frame's true box).
For every keyframe left out of the registered map, the registered keyframe sharing most
detected objects with it is taken and printed: the objects both detected, the matcher's
matches and how many of them are right, and the inliers of the relative pose verified from
them now (the view graph needs ``min_retrieved_inliers`` of them between separate views).
"""
import argparse
from collections import Counter

import numpy as np

from rfm_core.evaluation.pipeline import detections_for
from rfm_core.evaluation.suite import eval_configs
from rfm_core.geometry import iou_3d
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.session import Session
from rfm_core.sim.capture import Capture


def _objects(obs, truth) -> np.ndarray:
    """(N,) the room object each detection overlaps best (IoU3D >= 0.2), -1: none."""
    boxes, ids = truth
    out = np.full(len(obs.boxes), -1)
    if len(boxes) and len(obs.boxes):
        iou = iou_3d(obs.boxes, boxes)
        best = np.argmax(iou, axis=1)
        hit = iou[np.arange(len(best)), best] >= 0.2
        out[hit] = np.asarray(ids)[best[hit]]
    return out


def scene(config) -> Counter:
    detect = detections_for('depth_clusters')
    session = Session(MapperConfig())
    truth = {}
    for frame in Capture(config).frames():
        obs = detect(frame)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1
        truth[obs.stamp_ns] = (frame.ground_truth.boxes, frame.ground_truth.object_ids)
        session.step(obs)
    session.finish()
    graph, registered = session.graph, set(session.mapper.poses)
    views = {k.keyframe_id: k.observations for k in graph.keyframes}
    objects = {k: _objects(o, truth[o.stamp_ns]) for k, o in views.items()}
    seen = {k: set(v[v >= 0].tolist()) for k, v in objects.items()}
    counts = Counter()
    print(f'seed {config.seed} ({config.capture}): {len(views)} keyframes, {len(registered)} registered')
    for k in sorted(set(views) - registered):
        partner = max(sorted(registered), key=lambda j: len(seen[k] & seen[j]), default=None)
        if partner is None:
            continue
        shared = len(seen[k] & seen[partner])
        matches = graph.matcher.match(views[k], views[partner])
        right = sum(1 for a, b in zip(matches.a, matches.b)
                    if objects[k][a] >= 0 and objects[k][a] == objects[partner][b])
        rel = graph._relative(views[partner], views[k], matches, stream=False)
        inliers = 0 if rel is None else len(rel.inliers)
        print(f'  keyframe {k}: {len(views[k])} detections ({int((objects[k] >= 0).sum())} of room objects); '
              f'registered keyframe {partner}: {shared} objects detected in both, {len(matches)} matches, '
              f'{right} right, {inliers} verified')
        counts[f'{min(shared, 3)}{"+" if shared >= 3 else ""} shared'] += 1
        counts['right matches >= 2'] += right >= 2
        counts['verified >= 2'] += inliers >= 2
        counts[f'verified >= {graph.config.min_retrieved_inliers}'] += inliers >= graph.config.min_retrieved_inliers
    counts['unregistered'] += len(set(views) - registered)
    return counts


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('seeds', type=int, nargs='+')
    parser.add_argument('--first-seed', type=int, default=40, help="the suite's first seed (eval_configs)")
    args = parser.parse_args()
    configs = {c.seed: c for c in eval_configs(max(args.seeds) - args.first_seed + 1, first_seed=args.first_seed)}
    total = Counter()
    for seed in args.seeds:
        total += scene(configs[seed])
    print('all: ' + ', '.join(f'{k} {v}' for k, v in sorted(total.items())))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
