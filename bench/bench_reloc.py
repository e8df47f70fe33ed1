"""Relocalization against a map of a whole building: cost per query and accuracy as the map
grows to thousands of objects.

    ros_ws/env.sh python bench/bench_reloc.py [--rooms 80 --queried 10 --detector ground_truth:rgbd]

Each room (realistic world, seeds from 8000: outside the tuning and evaluation seeds) is
mapped in-process from a 30 s handheld walk at 2 Hz; the rooms' maps are placed side by side
(15 m apart) into one map (posed: each room's solved keyframe poses, shifted) of several
thousand objects, which is frozen (localization mode). A second walk through each of the
first ``--queried`` rooms (another path, 20 frames at 2 Hz, as ``rfm eval-reloc``) is
relocalized against the room's own map and against the building's: frame by frame (the
``rfm/relocalize`` service's way), and as a stream (localization mode's way,
:class:`rfm_core.mapping.localization.StreamLocalizer`, a fresh one per walk: the map's depth
points are merged when a walk first needs them, per map tile in the building). Reported:
relocalized and wrong (> 5 deg or > 25 cm, in the room's frame) per map, and the wall time
of one query on one core (median and 95th percentile, each the median over ``--repeats``
passes; the tracks are built once, before the first), and its ratio between the two maps per
pass.
"""
from __future__ import annotations

import os

for _var in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

SPACING_M = 15.0


def room_config(seed: int):
    from rfm_core.evaluation.suite import seed_config  # noqa: PLC0415
    return replace(seed_config(seed), capture='handheld', camera_height=(), frames=60, fps=2.0, width=320,
                   height=240, hfov_deg=70.0)


def offset(room: int) -> np.ndarray:
    """Where room ``room``'s map origin lies in the building's map (a 10-wide grid)."""
    return np.array([SPACING_M * (room % 10), SPACING_M * (room // 10), 0.0])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rooms', type=int, default=80)
    parser.add_argument('--queried', type=int, default=10)
    parser.add_argument('--query-frames', type=int, default=20)
    parser.add_argument('--detector', default='ground_truth:rgbd', help='for the maps and the queries')
    parser.add_argument('--first-seed', type=int, default=8000)
    parser.add_argument('--repeats', type=int, default=3, help='passes over the queries (latency: median of '
                        'the passes\' medians)')
    args = parser.parse_args()
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import detections_for, run_capture  # noqa: PLC0415
    from rfm_core.evaluation.suite import query_capture  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors  # noqa: PLC0415
    from rfm_core.geometry import Pose4  # noqa: PLC0415
    from rfm_core.mapping.localization import StreamLocalizer  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper, MapperConfig  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    torch.set_num_threads(1)
    building = Mapper(MapperConfig(posed=True), matcher=make_matcher('learned'))
    rooms = []                                   # (config, room mapper, T_world_map)
    start = time.perf_counter()
    for r in range(args.rooms):
        config = room_config(args.first_seed + r)
        result = run_capture(config, args.detector, noise_seed=3)
        mapped = result.mapper
        shift = Pose4(0.0, -offset(r))                                         # T_map_building
        base = 10_000 * r
        for k, obs in mapped.keyframes.items():
            building.add_keyframe(base + k, obs)
        for k, pose in mapped.poses.items():
            building.set_keyframe_pose(base + k, pose @ shift)
        for e in mapped.active_edges():
            building.add_edge(replace(e, source=base + e.source, target=base + e.target))
        if r < args.queried:
            rooms.append((config, mapped, map_to_truth(mapped.camera_poses(), result.truth)))
        print(f'room {r}: {len(mapped.poses)} keyframes, {len(mapped.tracks())} objects', flush=True)
    building.update()
    building.mode = 'localization'
    t0 = time.perf_counter()
    objects = len(building.tracks())
    build_s = time.perf_counter() - t0
    print(f'\nbuilding: {args.rooms} rooms, {len(building.poses)} keyframes, {objects} objects '
          f'(tracks built in {build_s:.1f} s; maps made in {time.perf_counter() - start:.0f} s)\n')
    detect = detections_for(args.detector, noise_seed=11)
    queries = []                                 # (room, frame index, true pose, detections)
    for r, (config, mapped, _) in enumerate(rooms):
        mapped.mode = 'localization'
        mapped.tracks()
        frames = Capture(query_capture(config, args.query_frames)).frames()
        queries += [(r, f.index, f.pose_matrix, detect(f)) for f in frames]
    results = {'room': ([], {}, {}), 'building': ([], {}, {})}
    for _ in range(args.repeats):
        for name in results:
            results[name][0].append([])
        for r, index, pose, obs in queries:
            world = rooms[r][2].matrix()
            back = Pose4(0.0, offset(r)).matrix()                              # room map <- building map
            maps = (('room', rooms[r][1], np.eye(4)), ('building', building, np.linalg.inv(back)))
            for name, mapper, to_room in maps:
                times, found, truth = results[name]
                truth[(r, index)] = pose
                t = time.perf_counter()
                reloc = mapper.relocalize(obs)
                times[-1].append(time.perf_counter() - t)
                if reloc is not None:
                    found[(r, index)] = world @ to_room @ reloc.camera_to_map(obs)
    # localization mode: each room's query walk as a stream (rfm_core.mapping.localization)
    by_stamp = {(r, obs.stamp_ns): index for r, index, _, obs in queries}
    for name in ('room', 'building'):
        results[f'{name} (stream)'] = ([], {}, {})
    for _ in range(args.repeats):
        for name in ('room', 'building'):
            results[f'{name} (stream)'][0].append([])
        for r in range(len(rooms)):
            world = rooms[r][2].matrix()
            back = Pose4(0.0, offset(r)).matrix()
            maps = (('room', rooms[r][1], np.eye(4)), ('building', building, np.linalg.inv(back)))
            for name, mapper, to_room in maps:
                times, found, truth = results[f'{name} (stream)']
                stream = StreamLocalizer(mapper)
                for rr, index, pose, obs in queries:
                    if rr != r:
                        continue
                    truth[(r, index)] = pose
                    t = time.perf_counter()
                    placed = stream.step(obs)
                    times[-1].append(time.perf_counter() - t)
                    for o, reloc in placed:
                        found[(r, by_stamp[(r, o.stamp_ns)])] = world @ to_room @ reloc.camera_to_map(o)
    print('| map | objects | query frames | relocalized | wrong | ARE median | ATE median | ms per query, '
          'median | p95 |')
    print('|---|---|---|---|---|---|---|---|---|')
    for name, (times, found, truth) in results.items():
        err = trajectory_errors(found, truth, align=False)
        count = objects if name.startswith('building') else statistics.median(len(m.tracks()) for _, m, _ in rooms)
        median = statistics.median(statistics.median(t) for t in times)
        p95 = statistics.median(sorted(t)[int(0.95 * (len(t) - 1))] for t in times)
        print(f'| {name} | {count:.0f} | {len(truth)} | {100 * err["registered"]:.1f}% | '
              f'{100 * err["wrong"]:.1f}% | {err["ARE_median"]:.2f} deg | {100 * err["ATE_median"]:.1f} cm | '
              f'{1e3 * median:.0f} | {1e3 * p95:.0f} |')
    ratios = [statistics.median(b) / statistics.median(a) for a, b in zip(results['room'][0], results['building'][0])]
    stream = [statistics.median(b) / statistics.median(a)
              for a, b in zip(results['room (stream)'][0], results['building (stream)'][0])]
    print(f'building / room, localization mode: {statistics.median(stream):.2f} (passes: '
          f'{", ".join(f"{x:.2f}" for x in stream)})')
    print(f'\nbuilding / room, median query time: {statistics.median(ratios):.2f} (passes: '
          f'{", ".join(f"{x:.2f}" for x in ratios)})')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
