"""How many frames of each `rfm eval` scene could be registered at all (#7's registered
target), given what the detector finds.

A frame can only join the map through objects it shares with other frames. This script
takes the detector's boxes on every frame of the `rfm eval` scenes (same seeds, same noise
seed), gives each box the identity of the true object it overlaps (3D IoU >= ``--min-iou``
in the frame, one-to-one as training labels them; others are anonymous), links two frames
when they share at least k identified objects, and reports the largest connected component's share of the frames
with >= 2 detections (the frames the pipeline considers). That is the registered share a
perfect matcher and a perfect verifier would reach under a k-object rule: k = 2 is the
paper's minimal sample, k = 3 what the view graph asks of an edge in an unordered
collection (sparse captures) and of any edge beyond the recent keyframes.

    ros_ws/env.sh python bench/registration_ceiling.py [--scenes 20] [--jobs 2]
"""
import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

DETECTORS = ('depth_clusters', 'ground_truth:rgbd')


def largest_component_share(objects: list, k: int) -> float:
    """Share of frames in the largest component when frames sharing >= k objects link."""
    n = len(objects)
    if n == 0:
        return 0.0
    ids = sorted(set().union(*objects))
    index = {o: i for i, o in enumerate(ids)}
    rows = [f for f, objs in enumerate(objects) for _ in objs]
    cols = [index[o] for objs in objects for o in objs]
    incidence = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, max(len(ids), 1)))
    shared = (incidence @ incidence.T).toarray()
    np.fill_diagonal(shared, 0)
    _, labels = connected_components(sp.csr_matrix(shared >= k), directed=False)
    return float(np.bincount(labels).max() / n)


def scene(args) -> dict:
    config, detectors, min_iou = args
    import torch  # noqa: PLC0415

    from rfm_core.evaluation.pipeline import detections_for  # noqa: PLC0415
    from rfm_core.training.matcher import assign_object_ids  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    torch.set_num_threads(1)
    frames = list(Capture(config).frames())
    out = {'scene': f'{config.seed}_{config.room_style}_{config.capture}', 'capture': config.capture}
    for spec in detectors:
        detect = detections_for(spec)
        objects = []
        for frame in frames:
            obs = detect(frame)
            if len(obs) < 2:
                continue                      # the view graph skips these frames
            ids = assign_object_ids(obs, frame.ground_truth, min_iou)
            objects.append({int(i) for i in ids if i >= 0})
        out[spec] = {k: largest_component_share(objects, k) for k in (2, 3)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenes', type=int, default=20)
    parser.add_argument('--first-seed', type=int, default=5000)
    parser.add_argument('--detectors', nargs='+', default=list(DETECTORS))
    parser.add_argument('--min-iou', type=float, default=0.25)
    parser.add_argument('--jobs', type=int, default=2)
    args = parser.parse_args()
    from rfm_core.evaluation.suite import eval_configs  # noqa: PLC0415

    work = [(c, tuple(args.detectors), args.min_iou) for c in eval_configs(args.scenes, args.first_seed, world='boxes')]
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(scene, work))
    print(f'Registered-share ceiling, {len(rows)} scenes from seed {args.first_seed} (min IoU {args.min_iou}):\n')
    print('| detector | captures | k = 2 (minimal sample) | k = 3 |\n|---|---|---|---|')
    for spec in args.detectors:
        for name, keep in (('handheld', 'handheld'), ('sparse', 'sparse'), ('all', None)):
            sel = [r[spec] for r in rows if keep is None or r['capture'] == keep]
            if sel:
                print(f'| {spec} | {name} | {100 * np.mean([s[2] for s in sel]):.1f}% | '
                      f'{100 * np.mean([s[3] for s in sel]):.1f}% |')
    print('\nper scene (k = 2 / k = 3):')
    for r in rows:
        print(r['scene'], '  '.join(f'{spec} {100 * r[spec][2]:.0f}/{100 * r[spec][3]:.0f}%' for spec in args.detectors))


if __name__ == '__main__':
    main()
