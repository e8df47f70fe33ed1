"""A change judged on the demo's scene without the graph's frame drops deciding: the same frame
subsets mapped in-process with two settings (an ablation; the product is `rfm run`).

    ros_ws/env.sh python bench/demo_subsets.py [--subsets 10] [--keep 0.6] \
        [--set matching.height_tolerance_m=0.0] [--cache /tmp/rfm_demo_subsets.pkl]

Renders the demo bag's scene (seed 11, plain room, handheld, 100 frames at 10 Hz; the
simulator's gravity and gyroscope), detects every frame once with ``depth_clusters``
(cached), then maps the whole capture and ``--subsets - 1`` random subsets of ``--keep`` of
its frames (as the graph keeps them on a slow machine) with the default settings and with
``--set`` (a field path of MapperConfig, ``matching.X``, ``averaging.X``, ..., or of the view
graph's KeyframeConfig, ``keyframes.X``), printing ARE /
ATE over the mapped frames and AP25 for both, side by side.
"""
import argparse
import copy
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np

from rfm_core.evaluation.mapping import evaluate_map
from rfm_core.evaluation.pipeline import detections_for
from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.view_graph import KeyframeConfig
from rfm_core.session import Session
from rfm_core.sim.capture import Capture, CaptureConfig


def with_setting(cfg, path: str, value):
    head, _, rest = path.partition('.')
    if not rest:
        return replace(cfg, **{head: type(getattr(cfg, head))(value)})
    return replace(cfg, **{head: with_setting(getattr(cfg, head), rest, value)})


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--subsets', type=int, default=10)
    parser.add_argument('--keep', type=float, default=0.6)
    parser.add_argument('--set', required=True, help='FIELD.PATH=VALUE for the second column: of MapperConfig, '
                        'or keyframes.NAME=VALUE of KeyframeConfig')
    parser.add_argument('--cache', default='/tmp/rfm_demo_subsets.pkl')
    args = parser.parse_args()
    capture = Capture(CaptureConfig(seed=11, room_style='plain', capture='handheld', frames=100, fps=10))
    cache = Path(args.cache)
    if cache.exists():
        frames = pickle.loads(cache.read_bytes())
    else:
        detect, frames = detections_for('depth_clusters'), []
        for f in capture.frames():
            obs = detect(f)
            obs.imu_rotation, obs.imu_epoch = f.rotation, 1
            frames.append((f.stamp_ns, f.pose_matrix, obs, f.ground_truth.object_ids, f.ground_truth.visibility))
        cache.write_bytes(pickle.dumps(frames))
    path, value = args.set.split('=', 1)
    value = {'true': True, 'false': False}.get(value.lower(), value)
    if path.startswith('keyframes.'):
        changed = (MapperConfig(), with_setting(KeyframeConfig(), path[len('keyframes.'):], value))
    else:
        changed = (with_setting(MapperConfig(), path, value), KeyframeConfig())
    variants = {'default': (MapperConfig(), KeyframeConfig()), args.set: changed}

    def run(keep, configs):
        session, truth = Session(*configs), {}
        visibility = np.zeros(len(capture.room.objects))
        for i in keep:
            stamp, pose, obs, ids, vis = frames[i]
            np.maximum.at(visibility, ids - 1, vis)
            truth[stamp] = pose
            session.step(copy.deepcopy(obs))
        tracks = session.finish()
        est = session.mapper.frame_poses()
        loc = trajectory_errors(est, truth, align='4dof')
        boxes = map_to_truth(est, truth).transform_boxes(np.array([t.box for t in tracks]).reshape(-1, 7))
        ap = evaluate_map(boxes, np.array([t.score for t in tracks]), capture.room.boxes, visibility < 0.2)['AP25']
        return loc['ARE_median'], 100 * loc['ATE_median'], ap

    rng = np.random.default_rng(0)
    print('| subset | ' + ' | '.join(f'{k}: ARE (deg) / ATE (cm) / AP25' for k in variants) + ' |')
    print('|---|' + '---|' * len(variants))
    results = {k: [] for k in variants}
    for n in range(args.subsets):
        keep = (np.sort(rng.choice(len(frames), int(args.keep * len(frames)), replace=False)) if n
                else np.arange(len(frames)))
        cells = []
        for name, config in variants.items():
            results[name].append(run(keep, config))
            cells.append('%.2f / %.1f / %.3f' % results[name][-1])
        print(f"| {'all frames' if n == 0 else n} | " + ' | '.join(cells) + ' |', flush=True)
    print('| median | ' + ' | '.join('%.2f / %.1f / %.3f' % tuple(np.median(results[k], 0)) for k in variants) + ' |')


if __name__ == '__main__':
    main()
