"""Detectors (paper section 3.1): per-frame metric 3D boxes with scores and embeddings.

Backends:

- ``depth_clusters`` — RGB-D, no learning (the default for RGB-D cameras);
- ``ground_truth`` — simulator ground truth with a noise model, for evaluating the back end;
- ``cutr`` — Cubify Transformer (PyTorch), loading the official checkpoints from a path.
"""
from __future__ import annotations

from dataclasses import replace

from rfm_core.detection.base import Detector, DetectorConfig, DetectorInput

__all__ = ['BACKENDS', 'Detector', 'DetectorConfig', 'DetectorInput', 'make_detector', 'detector_for_spec']

BACKENDS = ('depth_clusters', 'ground_truth', 'cutr')


def make_detector(backend: str, config: DetectorConfig | None = None, **options) -> Detector:
    """A detector by name, from that backend's config dataclass (``config``) and/or
    ``options`` (fields of it, replacing ``config``'s)."""
    if backend == 'depth_clusters':
        from rfm_core.detection.depth_clusters import DepthClustersConfig as Config
        from rfm_core.detection.depth_clusters import DepthClustersDetector as Detector_
    elif backend == 'ground_truth':
        from rfm_core.detection.ground_truth import GroundTruthConfig as Config
        from rfm_core.detection.ground_truth import GroundTruthDetector as Detector_
    elif backend == 'cutr':
        from rfm_core.detection.cutr import CutrConfig as Config
        from rfm_core.detection.cutr import CutrDetector as Detector_
    else:
        raise ValueError(f'unknown detector backend {backend!r}; choose one of {BACKENDS}')
    if config is not None and not isinstance(config, Config):
        raise TypeError(f'{backend} needs a {Config.__name__}, got {type(config).__name__}')
    return Detector_(replace(config, **options) if config is not None else Config(**options))


def detector_for_spec(spec: str, noise_seed: int = 0) -> Detector:
    """A detector from an evaluation spec: a backend name, ``ground_truth:PRESET``
    (``ground_truth`` alone: the rgbd preset) with ``noise_seed`` as its noise seed, or
    ``depth_clusters:heuristic`` (no learned box refiner)."""
    backend, _, preset = spec.partition(':')
    if backend == 'ground_truth':
        return make_detector('ground_truth', preset=preset or 'rgbd', seed=noise_seed)
    if backend == 'depth_clusters' and preset:
        variants = {'heuristic': {'box_refiner': ''}}
        if preset not in variants:
            raise ValueError(f'unknown depth_clusters variant {preset!r}: one of {sorted(variants)}')
        return make_detector(backend, **variants[preset])
    return make_detector(backend)
