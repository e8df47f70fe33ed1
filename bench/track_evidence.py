"""Re-score the maps of an `rfm eval --work DIR` run under view-evidence settings (#18 item 1).

    ros_ws/env.sh python bench/track_evidence.py WORK_DIR [--rates 0.3,0.02 0.5,0.05 ...]

For every scene of the run, the saved map (keyframes, edges, poses) is loaded and its object
tracks rebuilt with each (``tracks.detection_rate``, ``tracks.recurrence_rate``) pair and
``tracks.min_evidence`` 0 / 0.5, then scored against the bag's ground truth as `rfm eval`
does: AP25 (mean over scenes), map objects per room object (median) and the share of map
objects overlapping nothing real (IoU < 0.1, mean over scenes). No graph runs: the tracks
are the only thing that changes. Use it on tuning seeds (`rfm eval --first-seed 40`).
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from rfm_core.evaluation.mapping import evaluate_map
from rfm_core.evaluation.report import read_ground_truth
from rfm_core.evaluation.trajectory import map_to_truth
from rfm_core.mapping.map_io import load_map
from rfm_core.mapping.mapper import Mapper


def scenes(work: Path):
    """(name, mapper, ground truth, map -> truth alignment) of every scene with a map."""
    for d in sorted(p for p in work.iterdir() if p.is_dir()):
        run = next((p for p in sorted(d.iterdir()) if p.is_dir() and (p / 'map.rfm').exists()), None)
        if run is None or not (d / 'bag').exists():
            continue
        mapper = Mapper()
        load_map(mapper, run / 'map.rfm')
        truth = read_ground_truth(d / 'bag')
        frames = mapper.frame_poses() or {mapper.keyframes[k].stamp_ns: m for k, m in mapper.camera_poses().items()}
        yield d.name, mapper, truth, map_to_truth(frames, truth.camera_poses)


def score(mapper, truth, align, tracks_config, paper_score: bool = False) -> dict:
    """AP25, objects per room object and share of nothing real of the rebuilt tracks
    (``paper_score``: ranked by the paper's score, without the view evidence)."""
    mapper.config = dataclasses.replace(mapper.config, tracks=tracks_config)
    mapper._changed()
    tracks = mapper.tracks()
    scores = [t.quality if paper_score else t.score for t in tracks]
    boxes = align.transform_boxes(np.array([t.box for t in tracks]).reshape(-1, 7))
    ignore = np.array([truth.best_visibility.get(int(i), 0.0) < 0.2 for i in truth.ids], bool)
    m = evaluate_map(boxes, scores, truth.boxes, ignore)
    return {'AP25': m['AP25'], 'per_object': len(tracks) / max(int((~ignore).sum()), 1),
            'phantom': m['kinds']['phantom'] / max(len(tracks), 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('work', type=Path, help='an rfm eval --work folder')
    parser.add_argument('--rates', nargs='+', default=['0.3,0.05', '0.5,0.05', '0.7,0.05', '0.5,0.02', '0.5,0.1'],
                        help='detection_rate,recurrence_rate pairs')
    args = parser.parse_args()
    loaded = list(scenes(args.work))
    if not loaded:
        raise SystemExit(f'no scene with a map.rfm and a bag under {args.work}')
    base = loaded[0][1].config.tracks
    variants = [('every track, the paper\'s score', dataclasses.replace(base, min_evidence=0.0), True)]
    for pair in args.rates:
        p, q = (float(v) for v in pair.split(','))
        for least in (0.0, 0.5):
            variants.append((f'p {p} q {q} min_evidence {least}',
                             dataclasses.replace(base, detection_rate=p, recurrence_rate=q, min_evidence=least), False))
    print(f'{len(loaded)} scenes of {args.work}\n')
    print('| tracks | AP25 | objects / room object | nothing real |')
    print('|---|---|---|---|')
    for name, cfg, paper_score in variants:
        rows = [score(mapper, truth, align, cfg, paper_score) for _, mapper, truth, align in loaded]
        ap, per_object = np.mean([r['AP25'] for r in rows]), np.median([r['per_object'] for r in rows])
        print(f"| {name} | {ap:.3f} | {per_object:.2f} | {100 * np.mean([r['phantom'] for r in rows]):.0f}% |",
              flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
