"""Where `depth_clusters` puts the centre of a box the image border cuts (a diagnostic; the
product is `rfm run`).

Renders a capture (default: the demo bag's scene, seed 11, plain room, handheld, 100 frames
at 10 Hz), detects every ``--every``-th frame with ``depth_clusters``, associates each
detection with the visible true box it overlaps most (IoU3D >= 0.2), and prints, by which
image borders cut the detection's 2D box (within ``--margin`` pixels), the median error of
its centre along the viewing ray and across it (+ to the left), for the fitted box (what
relative poses use) and the refiner's full box (what the map uses).

    ros_ws/env.sh python bench/cut_boxes.py [--seed 11] [--style plain] [--every 3]
"""
import argparse
from collections import defaultdict

import numpy as np

from rfm_core.evaluation.pipeline import detections_for
from rfm_core.geometry import iou_3d
from rfm_core.sim.capture import Capture, CaptureConfig

SIDES = ((1, 'left'), (2, 'top'), (4, 'right'), (8, 'bottom'))


def border_cuts(boxes_2d, width: int, height: int, margin_px: float = 3.0) -> np.ndarray:
    """(N,) int: which image borders cut each detection's 2D box (x0, y0, x1, y1 pixels) as
    bits (1 left, 2 top, 4 right, 8 bottom): it reaches within ``margin_px`` of them."""
    b = np.asarray(boxes_2d, dtype=np.float64).reshape(-1, 4)
    return (np.stack([b[:, 0] <= margin_px, b[:, 1] <= margin_px, b[:, 2] >= width - 1 - margin_px,
                      b[:, 3] >= height - 1 - margin_px], 1).astype(int) @ np.array([1, 2, 4, 8]))


def cut_name(bits: int) -> str:
    return ' and '.join(name for bit, name in SIDES if bits & bit) or 'nothing'


def centre_errors(box, truth) -> tuple:
    """(along the viewing ray, across it: + to the left) of a box's centre against the truth's, m."""
    ray = truth[:2] / np.linalg.norm(truth[:2])
    d = box[:2] - truth[:2]
    return float(d @ ray), float(ray[0] * d[1] - ray[1] * d[0])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seed', type=int, default=11)
    parser.add_argument('--style', default='plain')
    parser.add_argument('--frames', type=int, default=100)
    parser.add_argument('--every', type=int, default=3)
    parser.add_argument('--margin', type=float, default=3.0, help='pixels from the border that count as cut')
    args = parser.parse_args()
    config = CaptureConfig(seed=args.seed, room_style=args.style, capture='handheld', frames=args.frames, fps=10)
    detect = detections_for('depth_clusters')
    rows = defaultdict(list)
    for frame in Capture(config).frames(range(0, args.frames, args.every)):
        obs, truth = detect(frame), frame.ground_truth
        if not len(obs) or not len(truth):
            continue
        iou = iou_3d(obs.boxes, truth.boxes)
        cuts = border_cuts(obs.boxes_2d, obs.intrinsics.width, obs.intrinsics.height, args.margin)
        for d in range(len(obs)):
            j = int(np.argmax(iou[d]))
            if iou[d, j] >= 0.2:
                rows[int(cuts[d])].append(centre_errors(obs.boxes[d], truth.boxes[j])
                                          + centre_errors(obs.map_boxes[d], truth.boxes[j]))
    print(f'| cut by | detections | fitted box: along / across (cm) | refiner\'s full box: along / across (cm) |')
    print('|---|---|---|---|')
    everything = np.concatenate([np.array(v) for v in rows.values()]) if rows else np.zeros((0, 4))
    for bits, values in [(-1, everything)] + sorted(((k, np.array(v)) for k, v in rows.items()), key=lambda kv: -len(kv[1])):
        med = 100 * np.median(values, axis=0)
        name = 'any (all detections)' if bits < 0 else cut_name(bits)
        print(f'| {name} | {len(values)} | {med[0]:+.1f} / {med[1]:+.1f} | {med[2]:+.1f} / {med[3]:+.1f} |')


if __name__ == '__main__':
    main()
