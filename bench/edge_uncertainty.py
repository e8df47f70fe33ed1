"""Is an edge's uncertainty calibrated? Every keyframe edge of the pair scenes, its predicted
standard deviations (:func:`rfm_core.matching.relative_pose.pose_uncertainty`) against its
error from the truth (#18 item 2; an ablation, the product is `rfm run`).

For the scenes of `bench/pair_accuracy.py` (the demo bag's scene and the handheld / robot
scenes among the tuning seeds 40-51, `depth_clusters` detections cached there) every frame
goes through :class:`rfm_core.session.Session` in-process. Printed: how well the predicted
yaw and translation standard deviations rank the edges by their true error (Spearman's rho;
against the inlier count alone, the averaging's weight before), and the errors in units of
the prediction (calibrated: the yaw's |z| has median 0.67, the horizontal translation's
|e| / sigma has RMS 1).

    ros_ws/env.sh python bench/edge_uncertainty.py [--cache /tmp/rfm_pair_accuracy]
"""
import argparse
import copy
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from pair_accuracy import frames_of, scenes
from rfm_core.geometry import wrap_angle
from rfm_core.mapping.frame_log import pose_from_camera
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.relative_pose import pose_uncertainty
from rfm_core.matching.view_graph import KeyframeConfig
from rfm_core.session import Session


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--cache', default='/tmp/rfm_pair_accuracy', help='detections per scene are kept here')
    args = parser.parse_args()
    rows = []                                    # (scene, inliers, sigma_yaw, sigma_t, yaw error, horizontal error)
    for name, config in scenes():
        session = Session(MapperConfig(), KeyframeConfig())
        matching = session.graph.matching
        truth, frame_truth, keyframes = {}, {}, {}
        for pose, obs in frames_of(name, config, Path(args.cache)):
            frame_truth[obs.stamp_ns] = pose
            step = session.step(copy.deepcopy(obs))
            if step.keyframe is not None:
                kf = step.keyframe.observations
                keyframes[step.keyframe.keyframe_id] = kf
                truth[step.keyframe.keyframe_id] = pose_from_camera(frame_truth[kf.stamp_ns], kf.gravity_cam, atol=0.2)
            for e in step.edges:
                rel = e.relative
                if not rel.num_matches or len(rel.inliers) < 2:           # motion edges rest on no object
                    continue
                actual = truth[e.source_id] @ truth[e.target_id].inverse()
                u = pose_uncertainty(rel.pose, keyframes[e.target_id].boxes, keyframes[e.source_id].boxes,
                                     rel.inliers[:, ::-1], matching)
                rows.append((name, len(rel.inliers), u.yaw_rad, u.translation_m,
                             abs(float(wrap_angle(rel.pose.yaw - actual.yaw))),
                             float(np.hypot(*(np.asarray(rel.pose.t) - actual.t)[:2]))))
        session.finish()
    n, s_yaw, s_t, e_yaw, e_t = (np.array([r[i] for r in rows], float) for i in range(1, 6))
    print(f'{len(rows)} keyframe edges on objects, {len({r[0] for r in rows})} scenes\n')
    print('| | Spearman rho with the yaw error | with the horizontal error |')
    print('|---|---|---|')
    print(f'| predicted sigma | {spearmanr(s_yaw, e_yaw)[0]:+.2f} | {spearmanr(s_t, e_t)[0]:+.2f} |')
    count = n ** -0.5
    print(f'| 1 / sqrt(inliers) (before) | {spearmanr(count, e_yaw)[0]:+.2f} | {spearmanr(count, e_t)[0]:+.2f} |')
    z_yaw, z_t = e_yaw / s_yaw, e_t / s_t
    print(f'\nyaw |error| / sigma: median {np.median(z_yaw):.2f} (0.67 if calibrated), '
          f'p90 {np.percentile(z_yaw, 90):.2f} (1.64); sigma median {np.degrees(np.median(s_yaw)):.2f} deg, '
          f'error median {np.degrees(np.median(e_yaw)):.2f} deg')
    print(f'horizontal |error| / sigma: RMS {np.sqrt(np.mean(z_t ** 2)):.2f} (1 if calibrated), '
          f'median {np.median(z_t):.2f} (0.83), p90 {np.percentile(z_t, 90):.2f} (1.52); '
          f'sigma median {100 * np.median(s_t):.1f} cm, error median {100 * np.median(e_t):.1f} cm')
    # the edges binned by predicted sigma: the error should grow with it
    for label, s, e, scale in (('yaw (deg)', s_yaw, e_yaw, np.degrees(1.0)), ('horizontal (cm)', s_t, e_t, 100.0)):
        q = np.quantile(s, [0, 0.25, 0.5, 0.75, 1.0])
        bins = np.clip(np.searchsorted(q, s, side='right') - 1, 0, 3)
        print(f'\n{label}: by quarter of predicted sigma, median predicted / RMS actual error: ' + ', '.join(
            f'{scale * np.median(s[bins == i]):.2f} / {scale * np.sqrt(np.mean(e[bins == i] ** 2)):.2f}'
            for i in range(4)))


if __name__ == '__main__':
    main()
