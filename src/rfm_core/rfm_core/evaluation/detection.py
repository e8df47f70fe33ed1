"""Per-frame 3D detection accuracy: AP and AR at 3D IoU thresholds (class-agnostic).

Each frame's detections are matched greedily by score to that frame's visible ground
truth (each ground-truth box at most once, exact yaw-oriented IoU). Ground-truth objects
seen less than ``min_visibility`` are "ignore" regions: a detection on one is neither a
true nor a false positive, and they are not counted in recall. AP is the all-point
interpolated area under the precision/recall curve. Results are averaged over frames (the
headline numbers, frames without ground truth skipped for AP) and also pooled over all
frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.geometry import boxes_from_oriented, gravity_aligned_rotation, iou_3d, oriented_from_boxes
from rfm_core.observations import FrameObservations

__all__ = ['THRESHOLDS', 'average_precision', 'match_detections', 'express_in',
           'DetectionEvaluator']

THRESHOLDS = (0.15, 0.25)


def average_precision(tp: np.ndarray, scores: np.ndarray, num_gt: int) -> float:
    """All-point interpolated AP of detections with true-positive flags and scores."""
    if num_gt == 0:
        return float('nan')
    if len(tp) == 0:
        return 0.0
    order = np.argsort(-np.asarray(scores), kind='stable')
    tp = np.asarray(tp, dtype=float)[order]
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    recall = ctp / num_gt
    precision = ctp / np.maximum(ctp + cfp, 1e-12)
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    steps = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


def match_detections(pred_boxes, pred_scores, gt_boxes, gt_ignore, threshold):
    """Greedy matching by score. Returns (tp flags (P,), counted mask (P,), matched GT count).

    ``counted`` is False for detections that only overlap ignored ground truth.
    """
    pred_boxes = np.asarray(pred_boxes).reshape(-1, 7)
    gt_boxes = np.asarray(gt_boxes).reshape(-1, 7)
    gt_ignore = np.asarray(gt_ignore, dtype=bool).reshape(-1)
    p = len(pred_boxes)
    tp = np.zeros(p, dtype=bool)
    counted = np.ones(p, dtype=bool)
    if p == 0 or len(gt_boxes) == 0:
        return tp, counted, 0
    ious = iou_3d(pred_boxes, gt_boxes)
    used = np.zeros(len(gt_boxes), dtype=bool)
    for i in np.argsort(-np.asarray(pred_scores), kind='stable'):
        cand = np.where(~used & ~gt_ignore, ious[i], -1.0)
        j = int(np.argmax(cand))
        if cand[j] >= threshold:
            tp[i] = True
            used[j] = True
        elif np.any(gt_ignore & (ious[i] >= threshold)):
            counted[i] = False
    return tp, counted, int(np.count_nonzero(used))


def express_in(obs: FrameObservations, gravity_cam) -> np.ndarray:
    """The full boxes of ``obs`` (:attr:`FrameObservations.map_boxes`) re-expressed in the
    gravity-aligned frame of another gravity estimate of the same camera (any residual tilt
    is projected away)."""
    if np.allclose(obs.gravity_cam, np.asarray(gravity_cam) / np.linalg.norm(gravity_cam), atol=1e-9):
        return obs.map_boxes
    r = gravity_aligned_rotation(gravity_cam) @ obs.rotation_aligned_from_camera.T
    centers, rotations, sizes = oriented_from_boxes(obs.map_boxes)
    return boxes_from_oriented(centers @ r.T, r @ rotations, sizes)


@dataclass
class _Tally:
    tp: list
    scores: list
    num_gt: int = 0
    matched: int = 0


class DetectionEvaluator:
    """Accumulate frames with :meth:`add`, then read :meth:`summary`."""

    def __init__(self, thresholds=THRESHOLDS, min_visibility: float = 0.2):
        self.thresholds = tuple(thresholds)
        self.min_visibility = float(min_visibility)
        self.frames = 0
        self._per_frame = {t: {'ap': [], 'ar': []} for t in self.thresholds}
        self._pooled = {t: _Tally([], []) for t in self.thresholds}

    def add(self, predictions: FrameObservations, ground_truth: FrameObservations) -> None:
        pred = express_in(predictions, ground_truth.gravity_cam)
        vis = ground_truth.visibility
        ignore = (vis >= 0) & (vis < self.min_visibility)
        num_gt = int(np.count_nonzero(~ignore))
        self.frames += 1
        for t in self.thresholds:
            tp, counted, matched = match_detections(pred, predictions.scores, ground_truth.boxes,
                                                    ignore, t)
            if num_gt:
                self._per_frame[t]['ap'].append(
                    average_precision(tp[counted], predictions.scores[counted], num_gt))
                self._per_frame[t]['ar'].append(matched / num_gt)
            pooled = self._pooled[t]
            pooled.tp.extend(tp[counted].tolist())
            pooled.scores.extend(predictions.scores[counted].tolist())
            pooled.num_gt += num_gt
            pooled.matched += matched

    def summary(self) -> dict:
        out = {'frames': self.frames}
        for t in self.thresholds:
            key = f'{int(round(t * 100))}'
            per = self._per_frame[t]
            pooled = self._pooled[t]
            out[f'AP{key}'] = float(np.mean(per['ap'])) if per['ap'] else float('nan')
            out[f'AR{key}'] = float(np.mean(per['ar'])) if per['ar'] else float('nan')
            out[f'pooled_AP{key}'] = average_precision(np.array(pooled.tp, bool),
                                                       np.array(pooled.scores), pooled.num_gt)
            out[f'pooled_AR{key}'] = pooled.matched / pooled.num_gt if pooled.num_gt else float('nan')
        return out
