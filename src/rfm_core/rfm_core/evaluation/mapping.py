"""Mapping accuracy as in the paper: scene-level AP/AR of the map's boxes at IoU 0.15/0.25.

The map's object boxes (with their track scores) are matched to the room's ground-truth
boxes. Ground-truth objects the capture never saw well (best visibility below
``min_visibility``) are ignore regions. Un-posed maps are first expressed in the ground
truth's frame by the 4-DoF (yaw + translation) alignment of the keyframe camera centres:
gravity is shared, and the paper aligns by SE(3) without scale.

Besides AP/AR, every map object is put in one of four kinds (:func:`object_kinds`): the
first box of a real object (matched at IoU 0.25, best score first), a duplicate of an object
already matched, a poor fit (best IoU 0.1-0.25), or overlapping nothing real (IoU < 0.1):
phantoms.

Labels (:func:`label_scores`): of the map objects that overlap a real object (IoU 0.25), the
share that carry its class, in NYU40's names (:mod:`rfm_core.detection.labels`), overall and
per class the map gives (precision).
"""
from __future__ import annotations

import numpy as np

from rfm_core.detection.labels import LabelMap
from rfm_core.evaluation.detection import THRESHOLDS, average_precision, match_detections
from rfm_core.geometry import iou_3d

__all__ = ['evaluate_map', 'object_kinds', 'label_scores', 'OBJECT_KINDS']

OBJECT_KINDS = ('real', 'duplicate', 'poor_fit', 'phantom')
PHANTOM_IOU = 0.1


def object_kinds(boxes, scores, gt_boxes, threshold: float = 0.25) -> dict:
    """How many map boxes are the first box of a real object, a duplicate, a poor fit or a
    phantom (see the module docstring); every ground-truth object counts, seen or not."""
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    gt_boxes = np.asarray(gt_boxes, float).reshape(-1, 7)
    counts = dict.fromkeys(OBJECT_KINDS, 0)
    if not len(boxes):
        return counts
    if not len(gt_boxes):
        counts['phantom'] = len(boxes)
        return counts
    ious = iou_3d(boxes, gt_boxes)
    tp, _, _ = match_detections(boxes, scores, gt_boxes, np.zeros(len(gt_boxes), bool), threshold)
    best = ious.max(1)
    counts['real'] = int(np.count_nonzero(tp))
    counts['duplicate'] = int(np.count_nonzero(~tp & (best >= threshold)))
    counts['poor_fit'] = int(np.count_nonzero((best >= PHANTOM_IOU) & (best < threshold)))
    counts['phantom'] = int(np.count_nonzero(best < PHANTOM_IOU))
    return counts


def label_scores(boxes, labels, gt_boxes, gt_labels, threshold: float = 0.25) -> dict:
    """``labelled``: map objects whose best IoU with a real object is at least ``threshold``;
    ``right``: those of them that carry that object's class; ``classes``: {name: [labelled,
    right]} by the name the map gives. Names compared as NYU40's (a detector's own or an NYU40
    name alike; see :mod:`rfm_core.detection.labels`)."""
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    gt_boxes = np.asarray(gt_boxes, float).reshape(-1, 7)
    out = {'labelled': 0, 'right': 0, 'classes': {}}
    if not len(boxes) or not len(gt_boxes):
        return out
    name = LabelMap()
    ious = iou_3d(boxes, gt_boxes)
    for i in np.flatnonzero(ious.max(1) >= threshold):
        given, true = name(labels[i]), name(gt_labels[int(ious[i].argmax())])
        counts = out['classes'].setdefault(given or '(none)', [0, 0])
        right = int(given == true)
        counts[0] += 1
        counts[1] += right
        out['labelled'] += 1
        out['right'] += right
    return out


def evaluate_map(boxes, scores, gt_boxes, gt_ignore=None, thresholds=THRESHOLDS, labels=None,
                 gt_labels=None) -> dict:
    """AP and AR of map boxes (N, 7) with scores against ground truth (M, 7); with both
    ``labels`` and ``gt_labels``, their :func:`label_scores` as ``labels``."""
    boxes = np.asarray(boxes, float).reshape(-1, 7)
    scores = np.asarray(scores, float).reshape(-1)
    gt_boxes = np.asarray(gt_boxes, float).reshape(-1, 7)
    ignore = np.zeros(len(gt_boxes), bool) if gt_ignore is None else np.asarray(gt_ignore, bool)
    num_gt = int(np.count_nonzero(~ignore))
    out = {'objects': len(boxes), 'ground_truth': num_gt}
    for t in thresholds:
        tp, counted, matched = match_detections(boxes, scores, gt_boxes, ignore, t)
        key = f'{int(round(t * 100))}'
        out[f'AP{key}'] = average_precision(tp[counted], scores[counted], num_gt)
        out[f'AR{key}'] = matched / num_gt if num_gt else float('nan')
    out['kinds'] = object_kinds(boxes, scores, gt_boxes)
    if labels is not None and gt_labels is not None and len(gt_labels) == len(gt_boxes):
        out['labels'] = label_scores(boxes, labels, gt_boxes, gt_labels)
    return out
