"""Every keyframe edge the view graph makes on the pair scenes, against the truth, and the
maps they give (an ablation; the product is `rfm run`).

For the scenes of `bench/pair_accuracy.py` (the demo bag's scene and the handheld / robot
scenes among the tuning seeds 40-51; `depth_clusters` detections cached there), every frame
goes through :class:`rfm_core.session.Session` in-process with the default settings. Printed
per scene: the keyframe edges resting on objects, their horizontal translation error (p50 /
p90), the median angle by which their horizontal translation is turned against the true one
(edges over 15 cm; + counter-clockwise), and the map's ARE / ATE median and frames localized
(4-DoF aligned). About 5 s once the detections are cached: the quick check of a change to
relative poses or keyframes before the offline suite (`rfm eval --offline`).

    ros_ws/env.sh python bench/keyframe_edges.py [--cache /tmp/rfm_pair_accuracy]
"""
import argparse
import copy
from pathlib import Path

import numpy as np

from pair_accuracy import cm_percentiles, frames_of, scenes
from rfm_core.evaluation.trajectory import trajectory_errors
from rfm_core.mapping.frame_log import pose_from_camera
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.view_graph import KeyframeConfig
from rfm_core.session import Session


def turned_deg(measured, actual) -> float:
    """Signed angle (deg) from the true horizontal translation to the measured one."""
    a, b = np.asarray(measured)[:2], np.asarray(actual)[:2]
    return float(np.degrees(np.arctan2(b[0] * a[1] - b[1] * a[0], a @ b)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cache', default='/tmp/rfm_pair_accuracy', help='detections per scene are kept here')
    args = parser.parse_args()
    print('| scene | edges | horizontal error p50 / p90 (cm) | turned, median (deg) | map ARE / ATE median, localized |')
    print('|---|---|---|---|---|')
    every_error, every_turn = [], []
    for name, config in scenes():
        session = Session(MapperConfig(), KeyframeConfig())
        truth, frame_truth, errors, turns = {}, {}, [], []
        for pose, obs in frames_of(name, config, Path(args.cache)):
            frame_truth[obs.stamp_ns] = pose
            step = session.step(copy.deepcopy(obs))
            if step.keyframe is not None:
                kf = step.keyframe.observations
                truth[step.keyframe.keyframe_id] = pose_from_camera(frame_truth[kf.stamp_ns], kf.gravity_cam, atol=0.2)
            for e in step.edges:
                if not e.relative.num_matches:                  # motion edges rest on no object
                    continue
                actual = (truth[e.source_id] @ truth[e.target_id].inverse()).t
                errors.append(float(np.hypot(*(np.asarray(e.relative.pose.t) - actual)[:2])))
                if np.hypot(*actual[:2]) > 0.15:
                    turns.append(turned_deg(e.relative.pose.t, actual))
        session.finish()
        loc = trajectory_errors(session.mapper.frame_poses(), frame_truth)
        every_error += errors
        every_turn += turns
        print(f'| {name} | {len(errors)} | {cm_percentiles(errors, (50, 90))} | '
              f'{np.median(turns):+.2f} | {loc["ARE_median"]:.2f} deg / {100 * loc["ATE_median"]:.1f} cm, '
              f'{100 * loc["registered"]:.0f}% |', flush=True)
    print(f'| all | {len(every_error)} | {cm_percentiles(every_error, (50, 90))} | {np.median(every_turn):+.2f} | |')


if __name__ == '__main__':
    main()
