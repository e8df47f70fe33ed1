"""Detectors (paper section 3.1): per-frame metric 3D boxes with scores and embeddings.

Backends:

- ``depth_clusters`` — RGB-D, no learning (the default for RGB-D cameras);
- ``ground_truth`` — simulator ground truth with a noise model, for evaluating the back end;
- ``cutr`` — Cubify Transformer (PyTorch), loading the official checkpoints from a path.
"""
from __future__ import annotations

from rfm_core.detection.base import Detector, DetectorConfig, DetectorInput

__all__ = ['BACKENDS', 'Detector', 'DetectorConfig', 'DetectorInput', 'make_detector', 'detector_for_spec']

BACKENDS = ('depth_clusters', 'ground_truth', 'cutr')


def make_detector(backend: str, **options) -> Detector:
    """A detector by name; ``options`` are fields of that backend's config dataclass."""
    if backend == 'depth_clusters':
        from rfm_core.detection.depth_clusters import DepthClustersConfig, DepthClustersDetector
        return DepthClustersDetector(DepthClustersConfig(**options))
    if backend == 'ground_truth':
        from rfm_core.detection.ground_truth import GroundTruthConfig, GroundTruthDetector
        return GroundTruthDetector(GroundTruthConfig(**options))
    if backend == 'cutr':
        from rfm_core.detection.cutr import CutrConfig, CutrDetector
        return CutrDetector(CutrConfig(**options))
    raise ValueError(f'unknown detector backend {backend!r}; choose one of {BACKENDS}')


def detector_for_spec(spec: str, noise_seed: int = 0) -> Detector:
    """A detector from an evaluation spec: a backend name, or ``ground_truth:PRESET``
    (``ground_truth`` alone: the rgbd preset) with ``noise_seed`` as its noise seed."""
    backend, _, preset = spec.partition(':')
    if backend == 'ground_truth':
        return make_detector('ground_truth', preset=preset or 'rgbd', seed=noise_seed)
    return make_detector(backend)
