"""A calibrated detection score for `depth_clusters`: P(box is right) from box features.

The detector's own score (points supporting the box, thinness, cut by the image border)
ranks boxes poorly on its own: a far, small, partly seen cluster can have as many points as
a near chair. A logistic model over a few resolution- and mounting-independent features —
the raw score, range, footprint sizes, height and angular image size, all as logs — turns
it into the probability that the box matches a visible object at 3D IoU >= 0.25: what
AP ranks by. The detector uses it to rank only; which boxes pass ``score_threshold`` is
still decided by the raw score (the learned matcher was trained on those boxes).

Trained by ``rfm train-depth-score`` on simulated scenes (seeds 3000+, the training
range; never the tuning or evaluation seeds); the shipped coefficients are a small JSON
file with the command that produced them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ['ScoreModel', 'box_features', 'DEFAULT_SCORE_MODEL', 'load_score_model', 'fit_score_model',
           'score_samples']

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


def score_samples(config) -> tuple:
    """(features, labels) of every depth_clusters box over one simulated capture: label 1
    when the box matches a ground-truth object seen >= 20% at IoU >= 0.25; boxes on objects
    seen less (the evaluation ignores them) are left out."""
    from rfm_core.detection.depth_clusters import DepthClustersConfig, DepthClustersDetector  # noqa: PLC0415
    from rfm_core.evaluation.detection import express_in  # noqa: PLC0415
    from rfm_core.geometry import iou_3d  # noqa: PLC0415
    from rfm_core.sim.capture import Capture  # noqa: PLC0415

    detector = DepthClustersDetector(DepthClustersConfig(score_model='', score_threshold=0.0))
    feats, labels = [], []
    for frame in Capture(config).frames():
        truth = frame.ground_truth
        pred = detector.detect(frame.detector_input())
        if not len(pred):
            continue
        ious = iou_3d(express_in(pred, truth.gravity_cam), truth.boxes) if len(truth.boxes) else \
            np.zeros((len(pred), 0))
        seen = truth.visibility >= 0.2
        hit = ious[:, seen].max(1) if seen.any() else np.zeros(len(pred))
        ignored = ious[:, ~seen].max(1) if (~seen).any() else np.zeros(len(pred))
        keep = ~((hit < IOU_THRESHOLD) & (ignored >= IOU_THRESHOLD))
        intr = pred.intrinsics
        feats.append(box_features(pred.scores, pred.boxes, pred.boxes_2d, intr.fx, intr.fy)[keep])
        labels.append(hit[keep] >= IOU_THRESHOLD)
    if not feats:
        return np.zeros((0, len(FEATURES))), np.zeros(0, bool)
    return np.concatenate(feats), np.concatenate(labels)


def fit_score_model(features: np.ndarray, labels: np.ndarray, l2: float = 1e-2) -> ScoreModel:
    """Logistic regression on standardised features (L-BFGS, a small L2 penalty)."""
    from scipy.optimize import minimize  # noqa: PLC0415

    x = np.asarray(features, np.float64)
    y = np.asarray(labels, np.float64)
    mean, std = x.mean(0), np.maximum(x.std(0), 1e-6)
    xn = np.c_[(x - mean) / std, np.ones(len(x))]

    def loss(w):
        z = xn @ w
        p = 1.0 / (1.0 + np.exp(-z))
        grad = xn.T @ (p - y) + 2 * l2 * np.r_[w[:-1], 0.0]
        return np.sum(np.logaddexp(0.0, z) - y * z) + l2 * np.sum(w[:-1] ** 2), grad

    w = minimize(loss, np.zeros(xn.shape[1]), jac=True, method='L-BFGS-B').x
    return ScoreModel(tuple(mean.round(6)), tuple(std.round(6)), tuple(w[:-1].round(6)), float(round(w[-1], 6)))
