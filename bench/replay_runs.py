"""Replay the detections an `rfm eval` run recorded through the in-process back end, and
score the frames it localizes (an ablation tool: the same detections for every variant).

    ros_ws/env.sh python bench/replay_runs.py WORK [--scenes 40_plain_handheld ...] [--json OUT]
    ros_ws/env.sh python bench/replay_runs.py WORK --setting map_run --bag map_bag   (rfm eval-reloc's mapping walks)

WORK is an `rfm eval --work WORK` directory (each scene's `bag` and the run's
`rgb_d__depth_clusters/outputs.mcap`, which holds every `rfm/detections` message the detector
published). A graph run is not repeatable: which frames the detector finishes, and which go
out with points only, changes from run to run, and single scenes swing by tens of points.
Replaying one run's recorded detections through :class:`rfm_core.session.Session` (the
matcher's and mapper's code, default parameters, no timing) is: two versions of the back end
compared on the same detections differ only by the code. Per scene: frames localized (of
the bag's frames), ARE / ATE medians and the share off by > 5 deg or > 25 cm (4-DoF aligned),
frames placed on their depth points alone, keyframes; then means / medians per capture.
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path)
    parser.add_argument('--scenes', nargs='*', help='scene folders of WORK (default: all with a recorded run)')
    parser.add_argument('--setting', default='rgb_d__depth_clusters', help="the run's folder in each scene")
    parser.add_argument('--bag', default='bag', help="the scene's bag folder (its ground truth scores the replay)")
    parser.add_argument('--json', type=Path, help='write the per-scene results here')
    args = parser.parse_args()
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
