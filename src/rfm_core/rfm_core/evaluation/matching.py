"""Matching and relative-pose accuracy on simulated frame pairs (paper 3.2-3.4).

Pairs of frames of rendered captures that share >= ``min_shared`` visible objects, with
detections from a backend whose ground-truth object ids give the true matches (see
:mod:`rfm_core.training.matcher`), are matched and their relative pose estimated and
verified. Reported: object-match precision and recall (a match is correct when both
detections belong to the same object; a match of two detections that are both no object,
such as two views of the same fragment, is not scored: it is no object match, yet it is
no error either; recall is over the objects detected in both frames) and F1, the fraction
of pairs verified, and the median yaw (deg) and translation (m) error of verified poses,
also over the verified pairs whose views turned by at least ``WIDE_TURN_DEG`` (partial boxes
seen from different sides: the edges that can rotate a map).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.geometry import wrap_angle
from rfm_core.matching.relative_pose import estimate_relative_pose

__all__ = ['PairResult', 'evaluate_pairs', 'WIDE_TURN_DEG']

#: a pair of views turned by this much (deg) or more counts as wide
WIDE_TURN_DEG = 60.0


@dataclass
class PairResult:
    pairs: int
    match_precision: float
    match_recall: float
    verified: float
    median_yaw_deg: float
    median_translation_m: float
    wide_pairs: int = 0                  #: verified pairs whose views turned >= WIDE_TURN_DEG
    median_yaw_deg_wide: float = float('nan')

    @property
    def f1(self) -> float:
        p, r = self.match_precision, self.match_recall
        return 2 * p * r / (p + r) if p + r > 0 else 0.0

    def row(self) -> str:
        return (f'{self.pairs} | {self.match_precision:.3f} | {self.match_recall:.3f} | {self.f1:.3f} | '
                f'{100 * self.verified:.1f}% | {self.median_yaw_deg:.2f} | '
                f'{100 * self.median_translation_m:.1f} | {self.wide_pairs} | {self.median_yaw_deg_wide:.2f}')


def evaluate_pairs(pairs, matcher, config=None) -> PairResult:
    """``pairs``: [(LabelledFrame a, LabelledFrame b), ...] (rfm_core.training.matcher)."""
    tp = fp = positives = 0
    verified, yaw_err, t_err, turn = 0, [], [], []
    for fa, fb in pairs:
        o1, o2 = fa.observations, fb.observations
        m = matcher.match(o1, o2)
        ia, ib = o1.object_ids[m.a], o2.object_ids[m.b]
        ok = (ia == ib) & (ia > 0)
        scored = (ia > 0) | (ib > 0)
        tp += int(ok.sum())
        fp += int((scored & ~ok).sum())
        positives += len(set(o1.object_ids[o1.object_ids > 0]) & set(o2.object_ids[o2.object_ids > 0]))
        rel = estimate_relative_pose(o1.boxes, o2.boxes, m, config)
        if rel is None:
            continue
        verified += 1
        truth = fb.aligned_from_map @ fa.aligned_from_map.inverse()        # T_b_a
        yaw_err.append(np.degrees(rel.pose.angle_to(truth)))
        t_err.append(float(np.linalg.norm(rel.pose.t - truth.t)))
        turn.append(float(np.degrees(abs(wrap_angle(truth.yaw)))))
    wide = np.asarray(turn) >= WIDE_TURN_DEG
    return PairResult(len(pairs), tp / max(tp + fp, 1), tp / max(positives, 1),
                      verified / max(len(pairs), 1),
                      float(np.median(yaw_err)) if yaw_err else float('nan'),
                      float(np.median(t_err)) if t_err else float('nan'),
                      int(wide.sum()), float(np.median(np.asarray(yaw_err)[wide])) if wide.any() else float('nan'))
