"""The soak's capture in one process: where do keyframes come from on a long walk, and does
the map stay straight? (#19 item 4; the graph's version is bench/soak.py)

    ros_ws/env.sh python bench/soak_offline.py [--minutes 5] [--fps 5] [--seed 7000]
                                               [--cache /tmp/rfm_soak_offline.pkl]
                                               [--no-culling] [--cull-min-views N]

Renders the soak's handheld walk (furniture made of parts, clutter; ~9 s a loop), detects
every frame with ``depth_clusters`` (cached: the first run takes a few minutes, later runs
about 15 s), runs :class:`rfm_core.session.Session` over all frames with the true gravity,
and prints the keyframes made by time, the keyframes and objects in the map by time (after
keyframe culling), how many of those made after the first 30 s had a keyframe within
``max_translation_m`` / ``max_yaw_deg`` already (true poses), the localization error of every
frame (4-DoF aligned) and the map's AP25 / AR25 against the room. A change to keyframe reuse
or culling can be judged here in seconds before the real-time soak.
"""
from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

import numpy as np


#: when counts are printed (seconds since the first frame)
MARKS_S = (10, 30, 60, 120, 300)


def _detections(args) -> list:
    if args.cache.is_file():
        cached = pickle.loads(args.cache.read_bytes())
        if cached['key'] == (args.minutes, args.fps, args.seed):
            return cached['frames']
    from rfm_core.evaluation.pipeline import detections_for  # noqa: PLC0415
    from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: PLC0415
    capture = Capture(CaptureConfig(seed=args.seed, capture='handheld', frames=int(round(args.minutes * 60 * args.fps)),
                                    fps=args.fps, furniture='parts', clutter=True))
    detect = detections_for('depth_clusters')
    frames = []
    for frame in capture.frames():
        obs = detect(frame)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1          # the gyroscope's, as the detector node attaches it
        frames.append((obs, frame.pose_matrix))
    args.cache.write_bytes(pickle.dumps({'key': (args.minutes, args.fps, args.seed), 'frames': frames}))
    return frames


def _heading(pose: np.ndarray) -> float:
    forward = pose[:3, 2]
    return float(np.arctan2(forward[1], forward[0]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--minutes', type=float, default=5.0)
    parser.add_argument('--fps', type=float, default=5.0)
    parser.add_argument('--seed', type=int, default=7000)
    parser.add_argument('--cache', type=Path, default=Path('/tmp/rfm_soak_offline.pkl'))
    parser.add_argument('--cycle-min-loops', type=int, default=None,
                        help='averaging.cycle_min_loops (default: the shipped one; 0: no cycle check)')
    parser.add_argument('--matcher', default='learned', help="object matcher: 'learned' (the nodes' default) or "
                        "'classical' (before session 26 this bench used the classical one)")
    parser.add_argument('--no-culling', action='store_true', help='culling.enabled:=false (keyframes are never culled)')
    parser.add_argument('--cull-min-views', type=int, default=None, help='culling.min_views (default: the shipped one)')
    args = parser.parse_args()
    from dataclasses import replace  # noqa: PLC0415

    from rfm_core.evaluation.mapping import evaluate_map  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors  # noqa: PLC0415
    from rfm_core.sim.capture import Capture, CaptureConfig  # noqa: PLC0415
    from rfm_core.mapping.mapper import MapperConfig  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.session import Session  # noqa: PLC0415

    frames = _detections(args)
    truth = {obs.stamp_ns: pose for obs, pose in frames}
    start_ns = frames[0][0].stamp_ns
    config = MapperConfig()
    if args.cycle_min_loops is not None:
        config = replace(config, averaging=replace(config.averaging, cycle_min_loops=args.cycle_min_loops))
    if args.no_culling:
        config = replace(config, culling=replace(config.culling, enabled=False))
    if args.cull_min_views is not None:
        config = replace(config, culling=replace(config.culling, min_views=args.cull_min_views))
    session = Session(config, matcher=make_matcher(args.matcher))          # the matcher node's default
    cfg = session.graph.config
    made, near = [], 0                                # (seconds, true pose) of each keyframe
    in_map = {}                                       # seconds -> keyframes in the map (after culling)
    objects = {}                                      # seconds -> objects in the map, at the marks
    t0, t_prev = time.perf_counter(), -1.0
    for obs, _ in frames:
        step = session.step(obs)
        t = (obs.stamp_ns - start_ns) / 1e9
        in_map[t] = len(session.mapper.keyframes)
        if any(t_prev < mark <= t for mark in MARKS_S):                # the first frame at or past a mark
            objects[t] = len(session.mapper.tracks())
        t_prev = t
        if step.keyframe is None:
            continue
        kf = step.keyframe.observations
        seconds, pose = (kf.stamp_ns - start_ns) / 1e9, truth[kf.stamp_ns]
        if seconds > 30 and made:
            d = np.array([np.linalg.norm(p[:3, 3] - pose[:3, 3]) for _, p in made])
            turn = np.array([abs((_heading(p) - _heading(pose) + np.pi) % (2 * np.pi) - np.pi) for _, p in made])
            near += bool(np.any((d <= cfg.max_translation_m) & (np.degrees(turn) <= cfg.max_yaw_deg)))
        made.append((seconds, pose))
    session.finish()
    seconds = time.perf_counter() - t0
    errors = trajectory_errors(session.mapper.frame_poses(), truth, align='4dof')
    times = np.array([s for s, _ in made])
    print('keyframes made by ' + ', '.join(f'{t} s: {int((times <= t).sum())}' for t in MARKS_S
                                           if t <= times.max(initial=0) + 60))
    marks = [t for t in MARKS_S if t <= max(in_map)]
    print('keyframes in the map at ' + ', '.join(
        f'{t} s: {in_map[max(s for s in in_map if s <= t)]}' for t in marks)
        + f' (end: {len(session.mapper.keyframes)}, culled {len(session.mapper.merged)}); objects at '
        + ', '.join(f'{t:.0f} s: {n}' for t, n in objects.items()))
    late = int((times > 30).sum())
    print(f'after 30 s: {late} keyframes, {near} of them with a keyframe within {cfg.max_translation_m} m and '
          f'{cfg.max_yaw_deg} deg already; revisits {session.graph.stats.reused}, bridges {session.graph.stats.bridged}')
    tracks = session.mapper.tracks()
    room = Capture(CaptureConfig(seed=args.seed, capture='handheld', frames=len(frames), fps=args.fps,
                                 furniture='parts', clutter=True)).room
    boxes = map_to_truth(session.mapper.frame_poses(), truth).transform_boxes(
        np.array([t.box for t in tracks]).reshape(-1, 7))
    ap = evaluate_map(boxes, np.array([t.score for t in tracks]), room.boxes)
    print(f"frames localized {100 * errors['registered']:.0f}%, ARE {errors['ARE_median']:.2f} deg, "
          f"ATE {100 * errors['ATE_median']:.1f} cm; {len(tracks)} objects ({len(room.boxes)} in the room), "
          f"AP25 {ap['AP25']:.3f}, AR25 {ap['AR25']:.3f}; {seconds:.0f} s")
    averager = session.mapper.averager
    print(f'edges {len(averager.edges)}, {int((~averager.edges.active).sum())} inactive, of them '
          f'{averager.cycle_dropped} dropped by the last full solve\'s cycle check')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
