"""Offline detection evaluation on bags: the detector sees what the node would see.

Colour, depth and camera_info come from the camera topics, gravity from a low-pass of the
IMU (exactly as the node computes it), and only the scoring reads ``/ground_truth``.
"""
from __future__ import annotations

import time

import numpy as np

from rfm_core.detection.base import DetectorInput
from rfm_core.detection.gravity import GravityFilter
from rfm_core.evaluation.detection import DetectionEvaluator
from rfm_core.io.bag import iter_camera_frames
from rfm_core.io.images import depth_to_meters, image_to_rgb
from rfm_core.io.messages import camera_info_intrinsics, frame_detections_from_msg, imu_reading
from rfm_core.io.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS

__all__ = ['evaluate_bag', 'detector_inputs', 'TOPICS']

TOPICS = dict(color=CAMERA_TOPICS['color'], depth=CAMERA_TOPICS['depth'], info=CAMERA_TOPICS['color_info'],
              imu=CAMERA_TOPICS['imu'], ground_truth=GROUND_TRUTH_TOPICS['gt_detections'])


def detector_inputs(path, topics: dict | None = None, every: int = 1, imu_tau_s: float = 1.0,
                    with_depth: bool = True, extra_topics: tuple = ()):
    """Every ``every``-th frame of a bag as the detector node would see it: yields pairs of
    the synchronised frame (a dict of :func:`iter_camera_frames`) and its DetectorInput
    (gravity from the IMU low-pass, depth in metres), the input None while the filter is not
    yet ready or without ``with_depth``."""
    t = dict(TOPICS, **(topics or {}))
    gravity = GravityFilter(tau_s=imu_tau_s)
    for i, frame in enumerate(iter_camera_frames(path, t['color'], t['depth'] if with_depth else None, t['info'],
                                                 t['imu'], extra_topics=extra_topics)):
        for imu in frame['imu']:
            gravity.add(*imu_reading(imu))
        if i % every:
            continue
        if not (with_depth and gravity.ready):
            yield frame, None
            continue
        yield frame, DetectorInput(frame['stamp_ns'], frame['color'].header.frame_id,
                                   camera_info_intrinsics(frame['info']), gravity.gravity(),
                                   image_to_rgb(frame['color']), depth_to_meters(frame['depth']))


def evaluate_bag(path, detector, evaluator: DetectionEvaluator | None = None, every: int = 1,
                 max_frames: int | None = None, topics: dict | None = None,
                 imu_tau_s: float = 1.0) -> dict:
    """Run ``detector`` over a bag and score it per frame; returns the evaluator's summary
    plus the median per-frame latency (ms) and frame count."""
    t = dict(TOPICS, **(topics or {}))
    evaluator = evaluator or DetectionEvaluator()
    latencies = []
    ground_truth_only = detector.name == 'ground_truth'
    for frame, inp in detector_inputs(path, t, every, imu_tau_s, with_depth=not ground_truth_only,
                                      extra_topics=(t['ground_truth'],)):
        if max_frames is not None and len(latencies) >= max_frames:
            break
        if inp is None and not ground_truth_only:
            continue
        truth = frame_detections_from_msg(frame[t['ground_truth']])
        start = time.perf_counter()
        pred = detector.perturb(truth) if ground_truth_only else detector.detect(inp)
        latencies.append(time.perf_counter() - start)
        evaluator.add(pred, truth)
    out = evaluator.summary()
    out['latency_ms'] = float(1e3 * np.median(latencies)) if latencies else float('nan')
    return out
