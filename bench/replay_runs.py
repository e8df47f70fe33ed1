"""Replay the detections an `rfm eval` run recorded through the in-process back end, and
score the frames it localizes (an ablation tool: the same detections for every variant).

    ros_ws/env.sh python bench/replay_runs.py WORK [--scenes 40_plain_handheld ...] [--json OUT]
    ros_ws/env.sh python bench/replay_runs.py WORK --setting map_run --bag map_bag   (rfm eval-reloc's mapping walks)
    ros_ws/env.sh python bench/replay_runs.py WORK --reloc [--verbose]   (rfm eval-reloc's query walks)

WORK is an `rfm eval --work WORK` directory (each scene's `bag` and the run's
`rgb_d__depth_clusters/outputs.mcap`, which holds every `rfm/detections` message the detector
published). A graph run is not repeatable: which frames the detector finishes, and which go
out with points only, changes from run to run, and single scenes swing by tens of points.
Replaying one run's recorded detections through :class:`rfm_core.session.Session` (the
matcher's and mapper's code, default parameters, no timing) is: two versions of the back end
compared on the same detections differ only by the code. Per scene: frames localized (of
the bag's frames), ARE / ATE medians and the share off by > 5 deg or > 25 cm (4-DoF aligned),
frames placed on their depth points alone, keyframes; then means / medians per capture.

``--reloc``: WORK is an ``rfm eval-reloc --work WORK`` directory. Each room's saved map
(``map_run/map.rfm``, the graph's) is loaded in localization mode and the query walk's
recorded detections (``query_run``) are localized as a stream, scored as ``rfm eval-reloc``
scores the graph (the map aligned to the world by its keyframes; #20's denominator: the query
frames that see two mapped objects; wrong: > 5 deg or > 25 cm). Localization against a
frozen map is deterministic: the same detections give the graph's result.
``--verbose`` lists each missed frame of the denominator with the reason, and each wrong pose.
"""
import argparse
import json
from pathlib import Path

import numpy as np

from rfm_core.evaluation.report import read_ground_truth
from rfm_core.evaluation.trajectory import trajectory_errors
from rfm_core.io.bag import topic_messages
from rfm_core.io.messages import frame_detections_from_msg
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.matching.factory import make_matcher
from rfm_core.session import Session


def recorded_detections(run: Path) -> list:
    """The FrameObservations of every ``rfm/detections`` message a run recorded, by stamp."""
    out = [frame_detections_from_msg(msg) for msg in topic_messages(run / 'outputs.mcap', '/rfm/detections')]
    return sorted(out, key=lambda o: o.stamp_ns)


def replay(scene: Path, setting: str = 'rgb_d__depth_clusters', bag: str = 'bag', matcher: str = 'learned') -> dict:
    """One scene's recorded detections through a Session; its localization scored."""
    observations = recorded_detections(scene / setting)
    truth = read_ground_truth(scene / bag).camera_poses
    session = Session(MapperConfig(), matcher=make_matcher(matcher))
    for obs in observations:
        session.step(obs)
    session.finish()
    errors = trajectory_errors(session.mapper.frame_poses(), truth, gross=(5.0, 0.25))
    return {'scene': scene.name, 'frames': len(truth), 'detections': len(observations),
            'registered': errors['registered'], 'ARE_median': errors['ARE_median'],
            'ATE_median': errors['ATE_median'], 'wrong': errors['wrong'],
            'point_tracked': session.graph.stats.point_tracked, 'keyframes': len(session.mapper.keyframes)}


def replay_reloc(scene: Path, verbose: bool = False) -> dict:
    """One room of an ``rfm eval-reloc`` run: its query walk's detections localized against
    its saved map (see the module)."""
    from rfm_core.evaluation.suite import relocalization_scores  # noqa: PLC0415
    from rfm_core.session import MapSession  # noqa: PLC0415

    session = MapSession(MapperConfig(), matcher=make_matcher('learned'))
    session.load(scene / 'map_run' / 'map.rfm')
    session.mode = 'localization'
    poses, why = {}, {}
    for obs in recorded_detections(scene / 'query_run'):
        for camera in session.localize(obs):
            poses[camera.stamp_ns] = camera.matrix
        why[obs.stamp_ns] = f'{len(obs)} detections: {session.message}'
    scores = relocalization_scores(session.mapper, scene / 'map_bag', scene / 'query_bag', poses)
    estimated, truth, seeing, row = scores.estimated, scores.truth, scores.seeing, scores.row
    if verbose:
        start = min(truth)
        for stamp in sorted(seeing - set(estimated)):
            print(f'    missed {(stamp - start) * 1e-9:5.1f} s: {why.get(stamp, "no detections recorded")}')
        for stamp, m in sorted(estimated.items()):
            d = np.linalg.inv(truth[stamp]) @ m
            deg = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
            if deg > 5 or np.linalg.norm(d[:3, 3]) > 0.25:
                print(f'    wrong  {(stamp - start) * 1e-9:5.1f} s: {deg:.1f} deg, {np.linalg.norm(d[:3, 3]):.2f} m')
    return {'scene': scene.name, 'seeing': len(seeing), 'found': len(seeing & set(estimated)),
            'relocalized': len(estimated), 'wrong': int(round(row['wrong'] * len(estimated))) if estimated else 0,
            'ARE_median': row['ARE_median'], 'ATE_median': row['ATE_median'], 'map_registered': row['map_registered']}


def main_reloc(work: Path, scenes, verbose: bool, json_path) -> int:
    rows = []
    chosen = [work / s for s in scenes] if scenes else sorted(p for p in work.iterdir() if (p / 'query_run').exists())
    for scene in chosen:
        r = replay_reloc(scene, verbose)
        rows.append(r)
        print(f"{r['scene']:26s} map {100 * r['map_registered']:3.0f}% registered  {r['found']:2d} of the "
              f"{r['seeing']:2d} frames that see two mapped objects  relocalized {r['relocalized']:2d}  wrong "
              f"{r['wrong']}  ARE {r['ARE_median']:5.2f} deg  ATE {100 * r['ATE_median']:5.1f} cm", flush=True)
    seeing, found = sum(r['seeing'] for r in rows), sum(r['found'] for r in rows)
    relocalized, wrong = sum(r['relocalized'] for r in rows), sum(r['wrong'] for r in rows)
    print(f'{len(rows)} rooms: {100 * found / max(seeing, 1):.1f}% of the {seeing} frames that see two mapped objects; '
          f'wrong {wrong} of {relocalized} ({100 * wrong / max(relocalized, 1):.1f}%); ARE '
          f'{np.nanmedian([r["ARE_median"] for r in rows]):.2f} deg, ATE '
          f'{100 * np.nanmedian([r["ATE_median"] for r in rows]):.1f} cm (medians of rooms)')
    if json_path:
        json_path.write_text(json.dumps(rows, indent=1, default=float))
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path)
    parser.add_argument('--scenes', nargs='*', help='scene folders of WORK (default: all with a recorded run)')
    parser.add_argument('--setting', default='rgb_d__depth_clusters', help="the run's folder in each scene")
    parser.add_argument('--bag', default='bag', help="the scene's bag folder (its ground truth scores the replay)")
    parser.add_argument('--json', type=Path, help='write the per-scene results here')
    parser.add_argument('--reloc', action='store_true', help="WORK is rfm eval-reloc's: replay its query walks")
    parser.add_argument('--verbose', action='store_true', help='--reloc: each missed and wrong frame')
    args = parser.parse_args()
    if args.reloc:
        return main_reloc(args.work, args.scenes, args.verbose, args.json)
    scenes = [args.work / s for s in args.scenes] if args.scenes else sorted(
        p for p in args.work.iterdir() if (p / args.setting / 'outputs.mcap').exists() and (p / args.bag).exists())
    rows = []
    for scene in scenes:
        r = replay(scene, args.setting, args.bag)
        rows.append(r)
        print(f"{r['scene']:26s} localized {100 * r['registered']:5.1f}%  ARE {r['ARE_median']:5.2f} deg  "
              f"ATE {100 * r['ATE_median']:5.1f} cm  wrong {100 * r['wrong']:5.1f}%  on points "
              f"{r['point_tracked']:4d}  keyframes {r['keyframes']}", flush=True)
    for capture in sorted({r['scene'].rsplit('_', 1)[-1] for r in rows}):
        sel = [r for r in rows if r['scene'].endswith('_' + capture)]
        mean = {k: float(np.nanmean([r[k] for r in sel])) for k in ('registered', 'ARE_median', 'ATE_median')}
        med = {k: float(np.nanmedian([r[k] for r in sel])) for k in ('ARE_median', 'ATE_median')}
        print(f"{capture} ({len(sel)}): localized {100 * mean['registered']:.1f}% mean; ARE {mean['ARE_median']:.2f} "
              f"mean / {med['ARE_median']:.2f} median deg; ATE {100 * mean['ATE_median']:.2f} mean / "
              f"{100 * med['ATE_median']:.2f} median cm")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
