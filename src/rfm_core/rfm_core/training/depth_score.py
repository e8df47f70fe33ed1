"""Fitting depth_clusters' calibrated detection score (:mod:`rfm_core.detection.score_model`)
on simulated scenes: ``rfm train-depth-score``."""
from __future__ import annotations

import numpy as np

from rfm_core.detection.depth_clusters import DepthClustersConfig, DepthClustersDetector
from rfm_core.detection.score_model import FEATURES, IOU_THRESHOLD, ScoreModel, box_features
from rfm_core.evaluation.detection import express_in
from rfm_core.geometry import iou_3d
from rfm_core.sim.capture import Capture

__all__ = ['score_samples', 'fit_score_model']


def score_samples(config) -> tuple:
    """(features, labels) of every depth_clusters box over one simulated capture: label 1
    when the box matches a ground-truth object seen >= 20% at IoU >= 0.25; boxes on objects
    seen less (the evaluation ignores them) are left out."""
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
