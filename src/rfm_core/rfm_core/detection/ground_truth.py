"""`ground_truth`: detections from a simulator's ground truth, with a documented noise model.

It exists to evaluate the back end (matching, averaging, mapping) under controlled
detector error; it is never a detector for a real camera. Input is the amodal ground-truth
boxes of the objects visible in a frame (``/ground_truth/detections``); output is what a
detector of a given quality would report.

Noise model, per detection (``z`` is the object's distance from the camera in m):

- missed with probability ``miss_rate + occlusion_miss * (1 - visibility)``;
- centre: Gaussian, std ``center_sigma_m + center_sigma_per_m * z`` per axis;
- depth scale (monocular-like): centre and size scaled by ``N(1, scale_sigma + scale_sigma_per_m * z)``
  along the viewing ray — the error an RGB-only detector makes when it misjudges distance;
- size: multiplied by ``N(1, size_sigma)`` per axis; yaw: Gaussian ``yaw_sigma_deg``;
- score: ``0.55 + 0.45 * visibility`` minus |N(0, score_sigma)|, clipped to [0.05, 1];
- embedding: a fixed vector per (label, size) — identical objects look identical — plus
  Gaussian noise ``embedding_sigma``, unit length;
- false positives: Poisson(``false_positives``) per frame, copies of visible objects moved
  by 0.5-1.5 m, with low scores.

Presets: ``perfect`` (no noise), ``rgbd`` (a good RGB-D detector), ``rgb`` (monocular:
depth-scale errors of several percent).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from rfm_core.detection.base import Detector, DetectorConfig, DetectorInput, finalize
from rfm_core.geometry import wrap_angle
from rfm_core.observations import FrameObservations
from rfm_core.settings import constant, setting

__all__ = ['GroundTruthNoise', 'PRESETS', 'GroundTruthConfig', 'GroundTruthDetector', 'EMBEDDING_DIM']

EMBEDDING_DIM = 32


@dataclass(frozen=True)
class GroundTruthNoise:
    miss_rate: float = 0.0
    occlusion_miss: float = 0.0
    center_sigma_m: float = 0.0
    center_sigma_per_m: float = 0.0
    scale_sigma: float = 0.0
    scale_sigma_per_m: float = 0.0
    size_sigma: float = 0.0
    yaw_sigma_deg: float = 0.0
    score_sigma: float = 0.0
    embedding_sigma: float = 0.0
    false_positives: float = 0.0


PRESETS = {
    'perfect': GroundTruthNoise(),
    'rgbd': GroundTruthNoise(miss_rate=0.03, occlusion_miss=0.3, center_sigma_m=0.01,
                             center_sigma_per_m=0.005, size_sigma=0.04, yaw_sigma_deg=2.0,
                             score_sigma=0.1, embedding_sigma=0.15, false_positives=0.3),
    'rgb': GroundTruthNoise(miss_rate=0.05, occlusion_miss=0.4, center_sigma_m=0.02,
                            center_sigma_per_m=0.01, scale_sigma=0.03, scale_sigma_per_m=0.01,
                            size_sigma=0.08, yaw_sigma_deg=4.0, score_sigma=0.15,
                            embedding_sigma=0.2, false_positives=0.5),
}


def _base_embedding(label: str, size) -> np.ndarray:
    """Deterministic appearance of an object: from its class and (sorted, rounded) size."""
    key = f'{label}:{",".join(f"{v:.2f}" for v in np.sort(size))}'
    rng = np.random.default_rng(zlib.crc32(key.encode()))
    v = rng.normal(size=EMBEDDING_DIM)
    return v / np.linalg.norm(v)


@dataclass(frozen=True)
class GroundTruthConfig(DetectorConfig):
    preset: str = setting('rgbd', 'Noise model of the simulated detections', choices=PRESETS)
    noise: GroundTruthNoise | None = constant(None, 'Overrides the preset when given')
    seed: int = setting(0, 'Seed of the simulated detection noise', lo=0, hi=2**31 - 1)


class GroundTruthDetector(Detector):
    name = 'ground_truth'
    needs_depth = False

    def __init__(self, config: GroundTruthConfig | None = None):
        self.config = config or GroundTruthConfig()
        if self.config.noise is None and self.config.preset not in PRESETS:
            raise ValueError(f'unknown ground_truth preset {self.config.preset!r}; '
                             f'choose one of {sorted(PRESETS)}')
        self.noise = self.config.noise or PRESETS[self.config.preset]
        self.monocular = self.noise.scale_sigma > 0 or self.noise.scale_sigma_per_m > 0
        self._seed = self.config.seed

    def detect(self, frame: DetectorInput) -> FrameObservations:
        raise TypeError('the ground_truth backend reads ground-truth detections, not images: '
                        'call perturb(ground_truth)')

    def perturb(self, truth: FrameObservations) -> FrameObservations:
        """Noisy detections from a frame's ground truth. Deterministic per (seed, stamp)."""
        nm = self.noise
        rng = np.random.default_rng([self._seed, int(truth.stamp_ns) & 0xFFFFFFFFFFFF])
        n = len(truth)
        vis = np.where(truth.visibility >= 0, truth.visibility, 1.0)
        keep = rng.random(n) >= nm.miss_rate + nm.occlusion_miss * (1.0 - vis)
        boxes = truth.boxes.copy()
        dist = np.linalg.norm(boxes[:, :3], axis=1)
        sigma = nm.center_sigma_m + nm.center_sigma_per_m * dist
        boxes[:, :3] += rng.normal(size=(n, 3)) * sigma[:, None]
        scale = 1.0 + rng.normal(size=n) * (nm.scale_sigma + nm.scale_sigma_per_m * dist)
        boxes[:, :3] *= scale[:, None]                  # along the ray from the camera
        boxes[:, 3:6] *= scale[:, None] * np.clip(1.0 + rng.normal(size=(n, 3)) * nm.size_sigma, 0.5, 1.5)
        boxes[:, 6] = wrap_angle(boxes[:, 6] + np.radians(nm.yaw_sigma_deg) * rng.normal(size=n))
        scores = np.clip(0.55 + 0.45 * vis - np.abs(rng.normal(size=n)) * nm.score_sigma, 0.05, 1.0)
        embeds = np.array([_base_embedding(label, size) for label, size in zip(truth.labels, truth.boxes[:, 3:6])]
                          ).reshape(n, EMBEDDING_DIM)
        embeds = embeds + rng.normal(size=embeds.shape) * nm.embedding_sigma / np.sqrt(EMBEDDING_DIM)
        labels = list(truth.labels)
        ids = truth.object_ids.copy()
        boxes_2d = truth.boxes_2d.copy()
        # false positives: visible objects copied somewhere else, with low scores
        extra = rng.poisson(nm.false_positives) if n and nm.false_positives > 0 else 0
        if extra:
            src = rng.integers(n, size=extra)
            fp = truth.boxes[src].copy()
            direction = rng.normal(size=(extra, 2))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            fp[:, :2] += direction * rng.uniform(0.5, 1.5, (extra, 1))
            boxes = np.concatenate([boxes, fp])
            scores = np.concatenate([scores, rng.uniform(0.2, 0.5, extra)])
            fp_emb = rng.normal(size=(extra, EMBEDDING_DIM))
            embeds = np.concatenate([embeds, fp_emb / np.linalg.norm(fp_emb, axis=1, keepdims=True)])
            labels += [labels[i] for i in src]
            ids = np.concatenate([ids, np.full(extra, -1)])
            boxes_2d = np.concatenate([boxes_2d, boxes_2d[src]])
            vis = np.concatenate([vis, np.zeros(extra)])
            keep = np.concatenate([keep, np.ones(extra, bool)])
        embeds /= np.maximum(np.linalg.norm(embeds, axis=1, keepdims=True), 1e-9)
        frame = DetectorInput(truth.stamp_ns, truth.frame_id, truth.intrinsics, truth.gravity_cam)
        sel = np.flatnonzero(keep)
        out = finalize(frame, boxes[sel], scores[sel], [labels[i] for i in sel], embeds[sel],
                       boxes_2d[sel], self.config, f'ground_truth:{self.config.preset}',
                       visibility=vis[sel], object_ids=ids[sel])
        return out
