"""Matching and relative-pose accuracy on simulated frame pairs (paper 3.2-3.4).

Pairs of frames of rendered captures, with detections from a backend (by default the
ground_truth noise presets, whose object ids give the true matches), are matched and
their relative pose estimated and verified. Reported: object-match precision and recall
(a match is correct when both detections belong to the same object), the fraction of
pairs verified, and the median yaw (deg) and translation (m) error of verified poses.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.matching.relative_pose import estimate_relative_pose
from rfm_core.sim.capture import Capture, CaptureConfig

__all__ = ['PairResult', 'evaluate_pairs']


@dataclass
class PairResult:
    pairs: int
    match_precision: float
    match_recall: float
    verified: float
    median_yaw_deg: float
    median_translation_m: float

    def row(self) -> str:
        return (f'{self.pairs} | {self.match_precision:.3f} | {self.match_recall:.3f} | '
                f'{self.verified:.3f} | {self.median_yaw_deg:.2f} | {100 * self.median_translation_m:.1f}')


def evaluate_pairs(detector, matcher, seeds, frames: int = 12, fps: float = 2.0, gap: int = 2,
                   min_shared: int = 3, config=None) -> PairResult:
    """Frames ``gap`` apart in captures of ``seeds`` sharing >= ``min_shared`` visible objects."""
    tp = fp = positives = 0
    verified, yaw_err, t_err = 0, [], []
    pairs = 0
    for seed in seeds:
        stream = list(Capture(CaptureConfig(seed=seed, frames=frames, fps=fps)).frames())
        for f1, f2 in zip(stream[:-gap], stream[gap:]):
            shared = set(f1.ground_truth.object_ids) & set(f2.ground_truth.object_ids)
            if len(shared) < min_shared:
                continue
            pairs += 1
            o1, o2 = detector.perturb(f1.ground_truth), detector.perturb(f2.ground_truth)
            m = matcher.match(o1, o2)
            ok = (o1.object_ids[m.a] == o2.object_ids[m.b]) & (o1.object_ids[m.a] > 0)
            tp += int(ok.sum())
            fp += int((~ok).sum())
            positives += len(set(o1.object_ids[o1.object_ids > 0]) & set(o2.object_ids[o2.object_ids > 0]))
            rel = estimate_relative_pose(o1.boxes, o2.boxes, m, config)
            if rel is None:
                continue
            verified += 1
            truth = f2.aligned_from_map() @ f1.aligned_from_map().inverse()        # T_2_1
            yaw_err.append(np.degrees(rel.pose.angle_to(truth)))
            t_err.append(float(np.linalg.norm(rel.pose.t - truth.t)))
    return PairResult(pairs, tp / max(tp + fp, 1), tp / max(positives, 1), verified / max(pairs, 1),
                      float(np.median(yaw_err)) if yaw_err else float('nan'),
                      float(np.median(t_err)) if t_err else float('nan'))
