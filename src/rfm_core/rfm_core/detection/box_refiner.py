"""A learned box refiner for `depth_clusters`: objectness, the amodal box and a
class from each cluster's points.

The heuristic detector (:mod:`rfm_core.detection.depth_clusters`) finds clusters of object
points and fits a box to each. On furniture made of parts (a table on legs, a chair with a
back, open shelves) and through an active-stereo camera's artefacts its clusters are often
fragments of an object, clutter or pieces of room structure, and its boxes stop at what is
visible. A small PointNet (Qi et al., 2017) reads each cluster — up to ``NUM_POINTS`` of its
points in the frame of the fitted box (position, normal, colour) plus a few global features
(the fitted box, range, height above the floor, flags) — and predicts

- **objectness**: the probability that the cluster is the main visible part of an object
  (fragments other than the largest, clutter and structure are negatives), used as the
  detection score;
- **the object's full box** as a correction of the fitted one: centre offset, log size
  ratio, yaw offset within +-45 deg (boxes are symmetric under quarter turns, sizes swap);
- **a class** out of :data:`CLASSES` (the simulator's object kinds).

Fragments other than an object's main part score low and fall below the detector's
threshold; non-maximum suppression over the published boxes (``nms_iou``) removes the
overlaps that remain (with predicted boxes: fragments that predict the same box). Trained by ``rfm train-box-refiner``
(:mod:`rfm_core.training.box_refiner`) on simulated scenes of training seeds; weights ship
in ``weights/box_refiner.npz`` with the command that produced them (numpy runs them:
:mod:`rfm_core.inference`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rfm_core.geometry import iou_3d, wrap_angle
from rfm_core.inference import linear, load_weights, relu, save_weights

__all__ = ['CLASSES', 'NUM_POINTS', 'POINT_FEATURES', 'GLOBAL_FEATURES', 'DEFAULT_BOX_REFINER', 'WEIGHTS_FORMAT',
           'RefinerNet', 'BoxRefiner', 'candidate_inputs', 'encode_target', 'decode_boxes', 'parameter_shapes',
           'save_box_refiner']

DEFAULT_BOX_REFINER = Path(__file__).parent / 'weights' / 'box_refiner.npz'
WEIGHTS_FORMAT = 'rfm-box-refiner'
CLASSES = ('bed', 'sofa', 'table', 'desk', 'cabinet', 'bookshelf', 'wardrobe', 'tv_stand', 'armchair',
           'nightstand', 'stool', 'bin', 'plant', 'chair', 'lamp', 'box', 'books', 'vase', 'monitor',
           'bowl', 'tv')
NUM_POINTS = 128
POINT_FEATURES = 9        # x, y, z in the fitted box's frame; normal (3); colour (3)
GLOBAL_FEATURES = 13
QUARTER = np.pi / 2


def _sample(n: int, k: int) -> np.ndarray:
    """k indices spread evenly over n points (repeated when n < k): points come in image
    order, so even spacing covers the whole cluster."""
    return np.linspace(0, n - 1, k).round().astype(int) if n >= k else np.arange(k) % n


def candidate_inputs(found, num_points: int = NUM_POINTS):
    """(points (N, num_points, POINT_FEATURES), globals (N, GLOBAL_FEATURES)) float32 inputs
    of the candidates of one frame (:class:`~rfm_core.detection.depth_clusters.Candidates`)."""
    items = found.items
    n = len(items)
    pts = np.zeros((n, num_points, POINT_FEATURES), np.float32)
    glob = np.zeros((n, GLOBAL_FEATURES), np.float32)
    intr = found.frame.intrinsics
    floor_z = found.floor_z
    for i, c in enumerate(items):
        box = c.box
        idx = _sample(len(c.points), num_points)
        cy, sy = np.cos(box[6]), np.sin(box[6])
        rot = np.array([[cy, sy, 0.0], [-sy, cy, 0.0], [0.0, 0.0, 1.0]])   # map -> box axes
        pts[i, :, 0:3] = (c.points[idx] - box[:3]) @ rot.T
        pts[i, :, 3:6] = c.normals[idx] @ rot.T
        if c.colours is not None:
            pts[i, :, 6:9] = c.colours[idx] / 255.0 - 0.5
        x0, y0, x1, y1 = c.box_2d
        glob[i] = [*np.log(np.maximum(box[3:6], 0.02)),
                   np.log(max(float(np.linalg.norm(box[:3])), 0.1)),
                   (box[2] - box[5] / 2 - floor_z) if floor_z is not None else 0.0,
                   floor_z is not None,
                   np.log(max(c.raw_score, 1e-3)),
                   np.log(len(c.points)) / 5.0,
                   c.truncated, c.on_support, c.bottom_hidden,
                   np.log(max(x1 - x0, 1.0) / intr.fx), np.log(max(y1 - y0, 1.0) / intr.fy)]
    return pts, glob


def encode_target(box, target) -> np.ndarray:
    """(8,) regression target of a true box relative to a fitted one: centre offset in the
    fitted box's axes (3), log size ratio (3), sin/cos of 4x the yaw offset (2); the yaw
    offset is taken within +-45 deg, sizes swapped with it."""
    box, target = np.asarray(box, np.float64), np.asarray(target, np.float64)
    d = float(wrap_angle(target[6] - box[6]))
    k = int(np.round(d / QUARTER))
    d -= k * QUARTER
    size = target[3:6].copy()
    if k % 2:
        size[[0, 1]] = size[[1, 0]]
    c, s = np.cos(box[6]), np.sin(box[6])
    off = target[:3] - box[:3]
    local = [c * off[0] + s * off[1], -s * off[0] + c * off[1], off[2]]
    return np.array([*local, *np.log(np.maximum(size, 0.02) / np.maximum(box[3:6], 0.02)),
                     np.sin(4 * d), np.cos(4 * d)])


def decode_boxes(boxes, deltas) -> np.ndarray:
    """Inverse of :func:`encode_target` for (N, 7) fitted boxes and (N, 8) predictions."""
    boxes, deltas = np.asarray(boxes, np.float64).reshape(-1, 7), np.asarray(deltas, np.float64).reshape(-1, 8)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    centre = boxes[:, :3] + np.stack([c * deltas[:, 0] - s * deltas[:, 1],
                                      s * deltas[:, 0] + c * deltas[:, 1], deltas[:, 2]], 1)
    size = np.maximum(boxes[:, 3:6], 0.02) * np.exp(np.clip(deltas[:, 3:6], -3.0, 3.0))
    yaw = wrap_angle(boxes[:, 6] + np.arctan2(deltas[:, 6], deltas[:, 7]) / 4)
    return np.concatenate([centre, size, yaw[:, None]], 1)


def parameter_shapes(width: int, classes: int = len(CLASSES)) -> dict:
    """{parameter name: shape} of the network (the names of the training module's state_dict)."""
    layers = {'point_mlp.0': (64, POINT_FEATURES, 1), 'point_mlp.2': (width, 64, 1),
              'point_mlp.4': (2 * width, width, 1), 'head.0': (2 * width, 2 * width + GLOBAL_FEATURES),
              'head.2': (width, 2 * width), 'head.4': (1 + 8 + classes, width)}
    return {k: v for name, shape in layers.items()
            for k, v in ((f'{name}.weight', shape), (f'{name}.bias', shape[:1]))}


class RefinerNet:
    """PointNet over a cluster's points (a shared MLP, max-pooled), joined with its global
    features; numpy forward pass of the training module's parameters."""

    def __init__(self, width: int, params: dict):
        self.width = int(width)
        self.params = params

    def __call__(self, points: np.ndarray, globals_: np.ndarray):
        """points (N, P, POINT_FEATURES), globals (N, GLOBAL_FEATURES) -> objectness logit (N,),
        box deltas (N, 8), class logits (N, classes)."""
        p = self.params
        feat = linear(relu(linear(relu(linear(points, p, 'point_mlp.0')), p, 'point_mlp.2')), p, 'point_mlp.4')
        x = np.concatenate([feat.max(axis=1), globals_], 1)
        out = linear(relu(linear(relu(linear(x, p, 'head.0')), p, 'head.2')), p, 'head.4')
        return out[:, 0], out[:, 1:9], out[:, 9:]


def save_box_refiner(width: int, params: dict, path, metadata: dict) -> None:
    """Write the refiner's parameters ({name: array}) with its description and ``metadata``."""
    save_weights(path, params, {'format': WEIGHTS_FORMAT, 'version': 2, 'width': int(width), 'classes': list(CLASSES),
                                'num_points': NUM_POINTS, 'metadata': metadata})


class BoxRefiner:
    """Refines one frame's candidates: ``refine(candidates) -> (boxes, scores, labels)``."""

    def __init__(self, net: RefinerNet, nms_iou: float = 0.3, num_points: int = NUM_POINTS):
        self.net = net
        self.nms_iou = float(nms_iou)
        self.num_points = int(num_points)

    @classmethod
    def load(cls, path='default', nms_iou: float = 0.3) -> 'BoxRefiner':
        path = DEFAULT_BOX_REFINER if path in ('default', None) else Path(path)

        def shapes(meta):
            if list(meta['classes']) != list(CLASSES):
                raise ValueError(f'classes {meta["classes"]} are not this version\'s')
            return parameter_shapes(int(meta['width']))
        params, meta = load_weights(path, WEIGHTS_FORMAT, 2, shapes, 'rfm train-box-refiner')
        num_points = meta.get('num_points')
        if not isinstance(num_points, int) or not 0 < num_points <= 4096:
            raise ValueError(f'{path}: num_points {num_points!r} is not a point count; '
                             'retrain with rfm train-box-refiner')
        return cls(RefinerNet(int(meta['width']), params), nms_iou, num_points)

    def refine(self, found):
        """(boxes (N, 7), objectness (N,), labels) for the candidates of one frame."""
        n = len(found.items)
        if not n:
            return np.zeros((0, 7)), np.zeros(0), []
        pts, glob = candidate_inputs(found, self.num_points)
        logit, deltas, cls_logits = self.net(pts, glob)
        boxes = decode_boxes(np.array([c.box for c in found.items]), deltas)
        scores = 1.0 / (1.0 + np.exp(-logit.astype(np.float64)))
        labels = [CLASSES[k] for k in cls_logits.argmax(1).tolist()]
        return boxes, scores, labels

    def suppress(self, boxes, scores) -> np.ndarray:
        """Indices of the boxes kept by greedy non-maximum suppression (best score first)."""
        order = np.argsort(-np.asarray(scores), kind='stable')
        if len(order) < 2:
            return order
        ious = iou_3d(boxes, boxes)
        keep = []
        for i in order:
            if all(ious[i, j] <= self.nms_iou for j in keep):
                keep.append(i)
        return np.array(keep, dtype=int)
