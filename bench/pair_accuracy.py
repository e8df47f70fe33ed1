"""Relative-pose accuracy of the view graph on frame pairs (an ablation; the product is `rfm run`).

For the demo bag's scene and the handheld / robot scenes among the tuning seeds 40-51 (the
realistic world of `rfm eval`), every frame is detected once with ``depth_clusters`` (cached;
the simulator's gyroscope), and frames 0.4, 0.8 and 1.6 s apart (one pair start every 0.2 s)
are matched and verified the way the view graph relates a frame to a keyframe
(``ViewGraphBuilder._relative``, stream: the gyroscope bounds the yaw; the nodes' learned
matcher unless ``--matcher classical``). Printed per scene: how many pairs verified a
relative pose and its horizontal translation / yaw error against the truth (p50 / p75 / p90),
and the same over the pairs whose frames both see a wall, with the walls
(``matching.wall_tolerance_m``, the default) and without them (boxes alone).

    ros_ws/env.sh python bench/pair_accuracy.py [--cache /tmp/rfm_pair_accuracy] [--matcher classical]
"""
import argparse
import copy
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np

from rfm_core.evaluation.pipeline import detections_for
from rfm_core.evaluation.suite import eval_configs
from rfm_core.geometry import wrap_angle
from rfm_core.mapping.frame_log import pose_from_camera
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.factory import make_matcher
from rfm_core.matching.view_graph import KeyframeConfig
from rfm_core.session import Session
from rfm_core.sim.capture import Capture, CaptureConfig


def scenes():
    out = [('demo', CaptureConfig(seed=11, room_style='plain', capture='handheld', frames=100, fps=10))]
    return out + [(f'{c.seed}_{c.capture}', c) for c in eval_configs(12, first_seed=40) if c.capture != 'sparse']


def frames_of(name, config, cache: Path):
    path = cache / f'{name}.pkl'
    if path.exists():
        frames = pickle.loads(path.read_bytes())
        if all(hasattr(obs, 'walls') for _, obs in frames):      # (a cache from before walls: redone)
            return frames
    detect, out = detections_for('depth_clusters'), []
    for f in Capture(config).frames():
        obs = detect(f)
        obs.imu_rotation, obs.imu_epoch = f.rotation, 1
        out.append((f.pose_matrix, obs))
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(out))
    return out


def cm_percentiles(distances, percents=(50, 75, 90)) -> str:
    """Percentiles of distances (m) in cm, as 'p50 / p75 / p90' ('nan' without any)."""
    return ' / '.join(f'{100 * np.percentile(distances, p) if len(distances) else float("nan"):.1f}'
                      for p in percents)


def deg_percentiles(angles, percents=(50, 75, 90)) -> str:
    return ' / '.join(f'{np.percentile(angles, p) if len(angles) else float("nan"):.2f}' for p in percents)


def row(name, verified, pairs, errors) -> str:
    """errors: {'all': [(dxy, dyaw)], 'walls': [...], 'boxes': [...]}."""
    cells = [f'{name}', f'{verified}/{pairs}']
    for key in ('all', 'walls', 'boxes'):
        e = np.array(errors[key]).reshape(-1, 2)
        cells += [f'{cm_percentiles(e[:, 0])} cm, {deg_percentiles(e[:, 1])} deg']
    cells.insert(3, str(len(errors['walls'])))
    return '| ' + ' | '.join(cells) + ' |'


def _error(rel, truth):
    d = np.asarray(rel.pose.t) - truth.t
    return float(np.hypot(d[0], d[1])), abs(float(np.degrees(wrap_angle(rel.pose.yaw - truth.yaw))))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cache', default='/tmp/rfm_pair_accuracy', help='detections per scene are kept here')
    parser.add_argument('--matcher', default='learned', choices=('learned', 'classical'))
    args = parser.parse_args()
    config = MapperConfig()
    matcher = make_matcher(args.matcher)
    graph = Session(config, KeyframeConfig(), matcher=matcher).graph
    boxes_only = Session(replace(config, matching=replace(config.matching, wall_tolerance_m=0.0)), KeyframeConfig(),
                         matcher=matcher).graph
    print('| scene | verified / pairs | horizontal / yaw error p50 / p75 / p90 | pairs seeing a wall | '
          'those with walls | those with boxes alone |')
    print('|---|---|---|---|---|---|')
    total = [0, 0, {'all': [], 'walls': [], 'boxes': []}]
    for name, capture in scenes():
        frames = frames_of(name, capture, Path(args.cache))
        step = max(int(round(capture.fps / 5)), 1)
        verified, pairs, errors = 0, 0, {'all': [], 'walls': [], 'boxes': []}
        for gap_s in (0.4, 0.8, 1.6):
            gap = max(int(round(gap_s * capture.fps)), 1)
            for i in range(0, len(frames) - gap, step):
                (pose_a, a), (pose_b, b) = frames[i], frames[i + gap]
                if len(a) < 2 or len(b) < 2:
                    continue
                pairs += 1
                rel = graph._relative(copy.deepcopy(a), copy.deepcopy(b), stream=True)   # T_a_b
                if rel is None:
                    continue
                verified += 1
                truth = (pose_from_camera(pose_a, a.gravity_cam, atol=0.2)
                         @ pose_from_camera(pose_b, b.gravity_cam, atol=0.2).inverse())
                errors['all'].append(_error(rel, truth))
                if len(a.walls) and len(b.walls):
                    plain = boxes_only._relative(copy.deepcopy(a), copy.deepcopy(b), stream=True)
                    if plain is not None:
                        errors['walls'].append(_error(rel, truth))
                        errors['boxes'].append(_error(plain, truth))
        print(row(name, verified, pairs, errors), flush=True)
        total[0] += verified
        total[1] += pairs
        for k in errors:
            total[2][k] += errors[k]
    print(row('all', *total))


if __name__ == '__main__':
    main()
