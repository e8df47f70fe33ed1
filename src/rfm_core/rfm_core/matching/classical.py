"""Classical object matcher: embedding similarity, a size gate, one-to-one assignment."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from rfm_core.matching.config import MatchingConfig
from rfm_core.observations import FrameObservations

__all__ = ['ObjectMatches', 'ClassicalMatcher', 'size_similarity']


@dataclass
class ObjectMatches:
    """Matched detection indices of frames a and b, with scores in [0, 1]."""

    a: np.ndarray
    b: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return len(self.a)


def size_similarity(boxes_a, boxes_b) -> np.ndarray:
    """(N, M) mean min/max ratio of the sorted footprint sizes and of the heights
    (rotation-invariant: yaw symmetries swap the footprint sizes)."""
    fa = np.sort(np.asarray(boxes_a)[:, 3:5], axis=1)
    fb = np.sort(np.asarray(boxes_b)[:, 3:5], axis=1)
    sa = np.c_[fa, np.asarray(boxes_a)[:, 5]][:, None, :]
    sb = np.c_[fb, np.asarray(boxes_b)[:, 5]][None, :, :]
    return np.mean(np.minimum(sa, sb) / np.maximum(np.maximum(sa, sb), 1e-9), axis=-1)


class ClassicalMatcher:
    """Mutual one-to-one matching (Hungarian) on cosine similarity of embeddings, gated by
    size similarity. Scores are (cosine + 1) / 2 times the size similarity."""

    def __init__(self, config: MatchingConfig | None = None):
        self.config = config or MatchingConfig()

    def match_many(self, a: FrameObservations, others) -> list:
        """``[match(a, b) for b in others]`` (the learned matcher batches this)."""
        return [self.match(a, b) for b in others]

    def match(self, a: FrameObservations, b: FrameObservations) -> ObjectMatches:
        cfg = self.config
        empty = ObjectMatches(np.zeros(0, int), np.zeros(0, int), np.zeros(0))
        if len(a) == 0 or len(b) == 0:
            return empty
        if a.embeddings.shape[1] and a.embeddings.shape[1] == b.embeddings.shape[1]:
            cosine = a.embeddings @ b.embeddings.T
        else:
            cosine = np.zeros((len(a), len(b)))
        sizes = size_similarity(a.boxes, b.boxes)
        score = (cosine + 1.0) / 2.0 * sizes
        score = np.where(sizes >= cfg.size_ratio_gate, score, 0.0)
        rows, cols = linear_sum_assignment(-score)
        keep = score[rows, cols] >= cfg.match_threshold
        return ObjectMatches(rows[keep], cols[keep], score[rows, cols][keep])
