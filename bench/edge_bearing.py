"""Whether a run's map turns its positions against its orientations (a diagnostic; the product
is `rfm run`).

For each `rfm run` output folder (its `map.rfm`: keyframes, edges and every localized frame)
on a bag with ground truth, printed:

- the yaw that aligns the run's trajectory to the truth from the orientations alone (the
  circular mean of the optical axes' heading differences) and from the camera positions alone
  (2D Kabsch of the centres), and their difference: a map whose relative yaws are right but
  whose translations are turned has positions and orientations that disagree, and the 4-DoF
  alignment (both together) leaves part of it in ARE and part in ATE;
- over the map's edge measurements resting on objects and at least 15 cm long: the signed
  angle between the measured horizontal translation and the true one (in the source
  keyframe's frame; positive counter-clockwise), their length ratio, and the yaw error;
- the edges' inlier matches split by whether the image border cuts their two boxes alike
  (`bench/cut_boxes.py`): how many, and their horizontal residual under the true relative
  pose (median).

    ros_ws/env.sh python bench/edge_bearing.py --bag bags/demo RUN [RUN ...]
"""
import argparse
from pathlib import Path

import numpy as np

from cut_boxes import border_cuts
from keyframe_edges import turned_deg
from rfm_core.evaluation.report import read_ground_truth
from rfm_core.evaluation.trajectory import align_4dof
from rfm_core.geometry import wrap_angle
from rfm_core.mapping.frame_log import pose_from_camera
from rfm_core.mapping.map_io import load_map
from rfm_core.mapping.mapper import Mapper


def heading(poses: np.ndarray) -> np.ndarray:
    """Heading (rad) of the optical axes of (N, 4, 4) camera-to-map poses."""
    return np.arctan2(poses[:, 1, 2], poses[:, 0, 2])


def load(run: Path) -> Mapper:
    mapper = Mapper()
    load_map(mapper, run / 'map.rfm')
    return mapper


def alignment_yaws(mapper: Mapper, truth) -> tuple:
    """(orientations only, positions only, both: the evaluation's 4-DoF) alignment yaws in deg."""
    est = mapper.frame_poses()
    keys = [k for k in est if k in truth.camera_poses]
    e = np.array([est[k] for k in keys])
    g = np.array([truth.camera_poses[k] for k in keys])
    orient = np.angle(np.mean(np.exp(1j * (heading(g) - heading(e)))))
    a, b = e[:, :2, 3] - e[:, :2, 3].mean(0), g[:, :2, 3] - g[:, :2, 3].mean(0)
    pos = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
    r, _ = align_4dof(e, g)
    return tuple(float(np.degrees(v)) for v in (orient, pos, np.arctan2(r[1, 0], r[0, 0])))


def keyframe_truth(mapper: Mapper, truth) -> dict:
    """{keyframe id: true Pose4 T_k_map} of the keyframes the bag's truth has a pose for."""
    return {k: pose_from_camera(truth.camera_poses[o.stamp_ns], o.gravity_cam, atol=0.3)
            for k, o in mapper.keyframes.items() if o.stamp_ns in truth.camera_poses}


def edge_errors(mapper: Mapper, true: dict) -> np.ndarray:
    """(E, 3): translation angle error (deg), length ratio, yaw error (deg) per edge measurement."""
    rows = []
    for e in mapper.measurements():
        if not len(e.inliers) or e.source not in true or e.target not in true:
            continue
        rel = true[e.source] @ true[e.target].inverse()
        measured, actual = np.asarray(e.pose.t)[:2], np.asarray(rel.t)[:2]
        if np.linalg.norm(actual) < 0.15:
            continue
        rows.append((turned_deg(measured, actual), np.linalg.norm(measured) / np.linalg.norm(actual),
                     np.degrees(wrap_angle(e.pose.yaw - rel.yaw))))
    return np.array(rows).reshape(-1, 3)


def median_cm(values) -> float:
    return 100 * float(np.median(values)) if len(values) else float('nan')


def cut_residuals(mapper: Mapper, true: dict) -> tuple:
    """Horizontal residuals (m) under the true relative pose of the edges' inlier matches
    whose boxes the border cuts alike in both keyframes, and of those it cuts differently."""
    cuts = {k: border_cuts(o.boxes_2d, o.intrinsics.width, o.intrinsics.height)
            for k, o in mapper.keyframes.items() if o.intrinsics is not None}
    alike, differently = [], []
    for e in mapper.measurements():
        if not len(e.inliers) or not {e.source, e.target} <= (true.keys() & cuts.keys()):
            continue
        rel = true[e.source] @ true[e.target].inverse()
        source, target = mapper.keyframes[e.source].boxes, mapper.keyframes[e.target].boxes
        for a, b in e.inliers:
            r = rel.transform_points(target[b, :3]) - source[a, :3]
            (alike if cuts[e.source][a] == cuts[e.target][b] else differently).append(float(np.hypot(*r[:2])))
    return alike, differently


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--bag', required=True, help='the bag the runs replayed (with /ground_truth topics)')
    parser.add_argument('runs', nargs='+', help='rfm run output folders')
    args = parser.parse_args()
    truth = read_ground_truth(args.bag)
    print('| run | alignment yaw: orientations / positions / both (deg) | positions - orientations (deg) '
          '| edges | translation turned, median [p25-p75] (deg) | length ratio median | yaw error median (deg) '
          '| inlier matches cut alike / differently: residual median (cm) |')
    print('|---|---|---|---|---|---|---|---|')
    for run in map(Path, args.runs):
        mapper = load(run)
        orient, pos, both = alignment_yaws(mapper, truth)
        true = keyframe_truth(mapper, truth)
        err = edge_errors(mapper, true)
        alike, differently = cut_residuals(mapper, true)
        q = np.percentile(err[:, 0], [50, 25, 75]) if len(err) else [float('nan')] * 3
        print(f'| {run.name} | {orient:.2f} / {pos:.2f} / {both:.2f} | {wrap_angle(np.radians(pos - orient)) * 180 / np.pi:+.2f} '
              f'| {len(err)} | {q[0]:+.2f} [{q[1]:+.2f} to {q[2]:+.2f}] | '
              f'{np.median(err[:, 1]) if len(err) else float("nan"):.3f} | '
              f'{np.median(err[:, 2]) if len(err) else float("nan"):+.2f} | '
              f'{len(alike)} / {len(differently)}: {median_cm(alike):.1f} / {median_cm(differently):.1f} |')


if __name__ == '__main__':
    main()
