"""A calibrated detection score for `depth_clusters`: P(box is right) from box features.

The detector's own score (points supporting the box, thinness, cut by the image border)
ranks boxes poorly on its own: a far, small, partly seen cluster can have as many points as
a near chair. A logistic model over a few resolution- and mounting-independent features —
the raw score, range, footprint sizes, height and angular image size, all as logs — turns
it into the probability that the box matches a visible object at 3D IoU >= 0.25: what
AP ranks by. The detector uses it to rank only; which boxes pass ``score_threshold`` is
still decided by the raw score (the learned matcher was trained on those boxes).

Trained by ``rfm train-depth-score`` (:mod:`rfm_core.training.depth_score`) on simulated
scenes (seeds 3000+, the training range; never the tuning or evaluation seeds); the shipped
coefficients are a small JSON file with the command that produced them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ['ScoreModel', 'box_features', 'DEFAULT_SCORE_MODEL', 'load_score_model', 'FEATURES', 'IOU_THRESHOLD']

DEFAULT_SCORE_MODEL = Path(__file__).parent / 'weights' / 'depth_clusters_score.json'
FEATURES = ('log raw score', 'log range', 'log footprint min', 'log footprint max', 'log height',
            'log angular width', 'log angular height')
IOU_THRESHOLD = 0.25


def box_features(raw_scores, boxes, boxes_2d, fx: float, fy: float) -> np.ndarray:
    """(N, len(FEATURES)) features of N boxes (gravity-aligned camera frame) and their
    image boxes (x0, y0, x1, y1 pixels)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 7)
    b2 = np.asarray(boxes_2d, np.float64).reshape(-1, 4)
    foot = np.sort(boxes[:, 3:5], axis=1)
    return np.stack([
        np.log(np.maximum(np.asarray(raw_scores, np.float64), 1e-3)),
        np.log(np.maximum(np.linalg.norm(boxes[:, :3], axis=1), 0.05)),
        np.log(np.maximum(foot[:, 0], 0.01)), np.log(np.maximum(foot[:, 1], 0.01)),
        np.log(np.maximum(boxes[:, 5], 0.01)),
        np.log(np.maximum(b2[:, 2] - b2[:, 0], 1.0) / fx),
        np.log(np.maximum(b2[:, 3] - b2[:, 1], 1.0) / fy)], 1)


@dataclass(frozen=True)
class ScoreModel:
    mean: tuple
    std: tuple
    weights: tuple
    bias: float

    def __call__(self, features: np.ndarray) -> np.ndarray:
        z = ((np.asarray(features) - np.array(self.mean)) / np.array(self.std)) @ np.array(self.weights) + self.bias
        return np.exp(-np.logaddexp(0.0, -z))            # sigmoid, without overflow

    def save(self, path, metadata: dict | None = None) -> None:
        data = {'features': list(FEATURES), 'mean': list(self.mean), 'std': list(self.std),
                'weights': list(self.weights), 'bias': self.bias, **(metadata or {})}
        Path(path).write_text(json.dumps(data, indent=1) + '\n')


def load_score_model(path=DEFAULT_SCORE_MODEL) -> ScoreModel:
    data = json.loads(Path(path).read_text())
    if data.get('features') != list(FEATURES):
        raise ValueError(f'{path}: a score model for features {data.get("features")}, this code '
                         f'computes {list(FEATURES)}; retrain with rfm train-depth-score')
    return ScoreModel(tuple(data['mean']), tuple(data['std']), tuple(data['weights']), float(data['bias']))
