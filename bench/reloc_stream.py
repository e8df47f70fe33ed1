"""Localization mode as a stream against each frame on its own (#20)

    ros_ws/env.sh rfm eval-reloc --scenes 10 --first-seed 40 --jobs 2 --work W
    ros_ws/env.sh python bench/reloc_stream.py W [--scenes 10 --first-seed 40] [--set NAME=VALUE ...]
        [--alt NAME=VALUE[,NAME=VALUE] ...] [--weights CHECKPOINT]

For each room of a graph-path `rfm eval-reloc` run kept in ``W``: the map the graph built
(``map_run/map.rfm``, with the mapper node's default learned matcher), and the second walk
detected again in-process (``depth_clusters``, the simulator's rotation as the gyroscope)
and localized twice in the same run: each frame relocalized on its own
(`relocalization.stream` off: the service's way), and as a stream
(`rfm_core.mapping.localization`: a track, and confirmation by a later frame). Prints, per
room and over all, the share relocalized (of all query frames and of #20's denominator, the
frames that see two mapped objects), the share wrong (> 5 deg or > 25 cm) and the median
errors. ``--set NAME=VALUE`` changes a ``relocalization`` setting of the stream run;
``--alt`` adds stream runs with other settings (the stream's settings are this code's
defaults, not the map file's). ``--weights``: the learned matcher's checkpoint for the
queries (the mapper node's ``relocalization.matcher_weights``; default: the shipped one).
"""
from __future__ import annotations

import argparse
from dataclasses import fields, replace
from pathlib import Path

import numpy as np


def localize(mapper, frames) -> dict:
    """{stamp: 4x4 camera-to-map} of the frames ``mapper``'s settings localize."""
    from rfm_core.mapping.localization import StreamLocalizer  # noqa: PLC0415

    stream = StreamLocalizer(mapper)
    out = {}
    for obs in frames:
        for o, reloc in stream.step(obs):
            out[o.stamp_ns] = reloc.camera_to_map(o)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path)
    parser.add_argument('--first-seed', type=int, default=40)
    parser.add_argument('--scenes', type=int, default=10)
    parser.add_argument('--query-frames', type=int, default=20)
    parser.add_argument('--set', nargs='*', default=[], metavar='NAME=VALUE',
                        help='relocalization settings of the stream run, e.g. stream_slack_m=0.5')
    parser.add_argument('--alt', nargs='*', metavar='NAME=VALUE[,NAME=VALUE]',
                        help='more stream runs, each with these settings')
    parser.add_argument('--weights', help="the queries' learned matcher checkpoint (default: the shipped one)")
    args = parser.parse_args()
    from rfm_core.evaluation.pipeline import detections_for  # noqa: PLC0415
    from rfm_core.evaluation.report import frames_seeing_mapped, map_boxes, read_ground_truth  # noqa: PLC0415
    from rfm_core.evaluation.suite import eval_configs, query_capture, scene_name  # noqa: PLC0415
    from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors  # noqa: PLC0415
    from rfm_core.mapping.map_io import load_map  # noqa: PLC0415
    from rfm_core.mapping.mapper import Mapper  # noqa: PLC0415
    from rfm_core.matching.factory import make_matcher  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    variants = {'each frame alone': {'stream': False}, 'stream': {}}
    for item in args.alt or []:
        variants[item] = dict(kv.split('=', 1) for kv in item.split(','))
    for item in args.set:
        name, value = item.split('=', 1)
        variants['stream'][name] = value
    defaults = Mapper().config.relocalization
    for changes in list(variants.values())[1:]:     # the stream's settings as this code has them, not the map file's
        for name in (f.name for f in fields(defaults) if f.name.startswith('stream')):
            changes.setdefault(name, getattr(defaults, name))
    for changes in variants.values():
        for name, value in changes.items():
            changes[name] = type(getattr(defaults, name))(value if value not in ('false', 'False') else '')
    totals = {v: [] for v in variants}
    for config in eval_configs(args.scenes, args.first_seed, capture='handheld'):     # as rfm eval-reloc's rooms
        scene = args.work / scene_name(config)
        if not (scene / 'map_run' / 'map.rfm').is_file():
            continue
        mapper = Mapper(matcher=make_matcher('learned', weights=args.weights))     # the mapper node's default
        load_map(mapper, scene / 'map_run' / 'map.rfm')
        mapper.mode = 'localization'
        base = mapper.config
        keyframes = {mapper.keyframes[k].stamp_ns: p for k, p in mapper.camera_poses().items()}
        alignment = map_to_truth(keyframes, read_ground_truth(scene / 'map_bag').camera_poses)
        world = alignment.matrix()
        seeing = frames_seeing_mapped(read_ground_truth(scene / 'query_bag'), map_boxes(mapper.tracks(), alignment))
        detect = detections_for('depth_clusters', noise_seed=11)
        frames, truth = [], {}
        for frame in Capture(query_capture(config, args.query_frames)).frames():
            frames.append(detect(frame))
            truth[frame.stamp_ns] = frame.pose_matrix
        line = [scene.name]
        for name, changes in variants.items():
            mapper.config = replace(base, relocalization=replace(base.relocalization, **changes))
            found = {s: world @ m for s, m in localize(mapper, frames).items()}
            err = trajectory_errors(found, truth, align=False, gross=(5.0, 0.25))
            n_wrong = int(round(err['wrong'] * len(found))) if found else 0
            totals[name].append((len(truth), len(found), len(seeing), len(seeing & set(found)), n_wrong,
                                 err['ARE_median'], err['ATE_median']))
            line.append(f'{name}: {len(found)}/{len(truth)} ({len(seeing & set(found))}/{len(seeing)} seeing), '
                        f'{n_wrong} wrong')
        print(' | '.join(line), flush=True)
    print('\n| localization | relocalized | of frames that see >= 2 mapped objects | wrong | ARE median of rooms '
          '(deg) | ATE median of rooms (cm) |\n|---|---|---|---|---|---|')
    for name, rows in totals.items():
        r = np.array(rows, float)
        print(f'| {name} | {100 * r[:, 1].sum() / r[:, 0].sum():.1f}% | {100 * r[:, 3].sum() / r[:, 2].sum():.1f}% '
              f'({int(r[:, 2].sum())}) | {100 * r[:, 4].sum() / max(r[:, 1].sum(), 1):.1f}% | '
              f'{np.nanmedian(r[:, 5]):.2f} | {100 * np.nanmedian(r[:, 6]):.1f} |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
