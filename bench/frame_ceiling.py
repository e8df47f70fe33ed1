"""How many frames of an `rfm eval` run could an object-level method localize at all?
(#15: frames localized; an analysis of a finished run, the product is `rfm run`)

    ros_ws/env.sh python bench/frame_ceiling.py WORK [--visibility 0.2]

WORK is an `rfm eval --work WORK` directory (each scene's bag and the run's outputs). Per
scene: its frames; those in which at least two objects of the room are visible (ground
truth, ``--visibility`` of each object at least; a relative pose needs two matched
objects); the frames the detector processed, and of them those with two detections or
more; the frames localized (`trajectory.tum`). Then the same over all scenes of each
capture. Frames localized can exceed the first count: a frame whose boxes are fragments,
clutter or pieces of wall may still be tracked (rightly or not).
"""
import argparse
from pathlib import Path

import numpy as np

from rfm_core.io.bag import topic_messages
from rfm_core.io.messages import stamp_to_ns


def _per_frame(bag: Path, topic: str) -> dict:
    """stamp_ns -> [visibility of each detection] of a detections topic (1.0 where it has none)."""
    if not bag.exists():
        return {}
    return {stamp_to_ns(msg.header.stamp): [float(getattr(d, 'visibility', 1.0)) for d in msg.detections]
            for msg in topic_messages(bag, topic)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path, help='an rfm eval --work directory')
    parser.add_argument('--visibility', type=float, default=0.2,
                        help="an object counts as visible in a frame from this share of it in view (the evaluation's "
                             'objects-ever-seen threshold)')
    args = parser.parse_args()
    print('| scene | frames | >= 2 objects visible | processed | processed with >= 2 detections | localized |')
    print('|---|---|---|---|---|---|')
    totals = {}
    for scene in sorted(p for p in args.work.iterdir() if (p / 'bag').is_dir()):
        runs = sorted(p for p in scene.iterdir() if (p / 'trajectory.tum').is_file())
        if not runs:
            continue
        truth = _per_frame(scene / 'bag', '/ground_truth/detections')
        detected = _per_frame(runs[0] / 'outputs.mcap', '/rfm/detections')
        localized = sum(1 for line in (runs[0] / 'trajectory.tum').read_text().splitlines()
                        if line.strip() and not line.startswith('#'))
        row = (len(truth), sum(sum(v >= args.visibility for v in vis) >= 2 for vis in truth.values()),
               len(detected), sum(len(v) >= 2 for v in detected.values()), localized)
        n = max(row[0], 1)
        print(f'| {scene.name} | {row[0]} | {100 * row[1] / n:.0f}% | {100 * row[2] / n:.0f}% | '
              f'{100 * row[3] / n:.0f}% | {100 * row[4] / n:.0f}% |')
        capture = scene.name.rsplit('_', 1)[-1]
        totals.setdefault(capture, []).append(np.array(row, float))
    for capture, rows in sorted(totals.items()):
        share = np.array([r[1:] / max(r[0], 1) for r in rows])        # per scene, as rfm eval averages
        print(f'| {capture} ({len(rows)}), mean over scenes | | ' + ' | '.join(f'{100 * v:.1f}%' for v in share.mean(0))
              + ' |')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
