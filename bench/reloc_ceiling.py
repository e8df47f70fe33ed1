"""Which query frames can relocalization find at all? (#20)

    ros_ws/env.sh rfm eval-reloc --scenes 8 --first-seed 40 --jobs 2 --work W
    ros_ws/env.sh python bench/reloc_ceiling.py W [--scenes 8 --first-seed 40]

For each room of a graph-path `rfm eval-reloc` run kept in ``W``: the map the graph built
(``map_run/map.rfm``), and each frame of the second walk detected again with
``depth_clusters`` (in-process) and placed at its *true* pose in the map: how many of its
detections land on the map's objects (`relocalization.explained`, IoU >= 0.25 with a track's
box or one of its views). A frame explaining fewer than `relocalization.min_explained` (4)
there cannot be relocalized by any pose the check accepts. Prints, by that count, the
frames and how many the graph relocalized: over all query frames, and over #20's
denominator, the frames that see two objects the map holds (`rfm eval-reloc`'s
"of frames that see >= 2 mapped objects").
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path)
    parser.add_argument('--first-seed', type=int, default=40)
    parser.add_argument('--scenes', type=int, default=8)
    parser.add_argument('--query-frames', type=int, default=20)
    args = parser.parse_args()
    from rfm_core.evaluation.pipeline import detections_for  # noqa: PLC0415
    from rfm_core.evaluation.report import frames_seeing_mapped, map_boxes, read_ground_truth  # noqa: PLC0415
    from rfm_core.evaluation.suite import camera_poses_of_run, eval_configs, query_capture, scene_name  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth  # noqa: PLC0415
    from rfm_core.mapping.frame_log import pose_from_camera  # noqa: PLC0415
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415
    from rfm_core.mapping.relocalization import explained  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    rows = []                                           # (detections, explained at the truth, relocalized)
    for config in eval_configs(args.scenes, args.first_seed, capture='handheld'):     # as rfm eval-reloc's rooms
        scene = args.work / scene_name(config)
        if not (scene / 'map_run' / 'map.rfm').is_file():
            continue
        mapper = Mapper()
        load_map(mapper, scene / 'map_run' / 'map.rfm')
        keyframes = {mapper.keyframes[k].stamp_ns: p for k, p in mapper.camera_poses().items()}
        alignment = map_to_truth(keyframes, read_ground_truth(scene / 'map_bag').camera_poses)
        to_map = np.linalg.inv(alignment.matrix())
        relocalized = camera_poses_of_run(scene / 'query_run')
        seeing = frames_seeing_mapped(read_ground_truth(scene / 'query_bag'), map_boxes(mapper.tracks(), alignment))
        index = mapper.map_index()
        detect = detections_for('depth_clusters', noise_seed=11)
        for frame in Capture(query_capture(config, args.query_frames)).frames():
            obs = detect(frame)
            pose = pose_from_camera(to_map @ frame.pose_matrix, obs.gravity_cam, atol=0.5)
            rows.append((len(obs), explained(obs, pose, index, mapper.config.matching) if len(obs) else 0,
                         frame.stamp_ns in relocalized, frame.stamp_ns in seeing))
    rows = np.array(rows, float).reshape(-1, 4)
    print('| detections explained at the true pose | frames | relocalized by the graph | median detections '
          '| frames that see two mapped objects | of them relocalized |')
    print('|---|---|---|---|---|---|')
    for lo, hi, label in ((0, 1, '0'), (1, 2, '1'), (2, 3, '2'), (3, 4, '3'), (4, 1000, '4 or more')):
        sel = (rows[:, 1] >= lo) & (rows[:, 1] < hi)
        seen = sel & (rows[:, 3] > 0)
        print(f'| {label} | {int(sel.sum())} | {int(rows[sel, 2].sum())} | '
              f'{np.median(rows[sel, 0]) if sel.any() else 0:.1f} | {int(seen.sum())} | {int(rows[seen, 2].sum())} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
