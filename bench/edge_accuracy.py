"""Accuracy of the view graph's keyframe edges by how they were measured (an ablation; the
product is `rfm run`).

For the scenes of `bench/pair_accuracy.py` (the demo bag's scene and the handheld / robot
scenes among the tuning seeds 40-51; every frame detected once with ``depth_clusters``,
cached; the simulator's gyroscope), every frame goes through the view graph in-process with
the default settings and ``keyframes.through_frames`` 2 (default 0). Of the keyframe pairs
measured both directly (the new keyframe matched against its reference) and through frames
tracked on the reference, printed per scene: the horizontal translation error
against the truth of the direct measurement and of the through ones (p50 / p75 / p90), and
how often the through measurements' median is nearer the truth than the direct one.

    ros_ws/env.sh python bench/edge_accuracy.py [--cache /tmp/rfm_pair_accuracy]
"""
import argparse
import copy
from pathlib import Path

import numpy as np

from pair_accuracy import cm_percentiles, frames_of, scenes
from rfm_core.mapping.frame_log import pose_from_camera
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.view_graph import KeyframeConfig
from rfm_core.session import Session


def error(edge, truth_of) -> float:
    """Horizontal error (m) of an edge's T_source_target against the truth."""
    d = np.asarray(edge.relative.pose.t) - (truth_of(edge.source_id) @ truth_of(edge.target_id).inverse()).t
    return float(np.hypot(d[0], d[1]))


def row(name, pairs, direct, through, nearer) -> str:
    return f'| {name} | {pairs} | {cm_percentiles(direct)} | {cm_percentiles(through)} | {nearer}/{pairs} |'


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cache', default='/tmp/rfm_pair_accuracy', help='detections per scene are kept here')
    args = parser.parse_args()
    print('| scene | pairs measured both ways | direct: error p50 / p75 / p90 (cm) | through: p50 / p75 / p90 (cm) '
          '| through median nearer |')
    print('|---|---|---|---|---|')
    total = [[], [], 0, 0]
    for name, config in scenes():
        graph = Session(MapperConfig(), KeyframeConfig(through_frames=2)).graph
        truth = {}
        direct, through, nearer, pairs = [], [], 0, 0
        for pose, obs in frames_of(name, config, Path(args.cache)):
            step = graph.add(copy.deepcopy(obs))
            if step.keyframe is None:
                continue
            truth[step.keyframe.keyframe_id] = pose_from_camera(pose, obs.gravity_cam, atol=0.2)
            by_pair = {}
            for e in step.edges:                         # the direct measurement first, then the through ones
                by_pair.setdefault((e.source_id, e.target_id), []).append(e)
            for measured in by_pair.values():
                if len(measured) < 2 or measured[0].trust < 1.0:
                    continue
                d = error(measured[0], truth.__getitem__)
                t = [error(e, truth.__getitem__) for e in measured[1:]]
                pairs += 1
                direct.append(d)
                through += t
                nearer += float(np.median(t)) < d
        print(row(name, pairs, direct, through, nearer), flush=True)
        total = [total[0] + direct, total[1] + through, total[2] + nearer, total[3] + pairs]
    direct, through, nearer, pairs = total
    print(row('all', pairs, direct, through, nearer))


if __name__ == '__main__':
    main()
