"""The detector interface (paper section 3.1: the "keypoint detector" of Rooms from Motion).

A detector turns one image (and optionally its registered depth) into metric,
gravity-aligned 3D boxes with scores and appearance embeddings, in the frame's
gravity-aligned camera frame (see :mod:`rfm_core.geometry`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.clouds import depth_cloud
from rfm_core.detection.labels import label_map
from rfm_core.observations import CameraIntrinsics, FrameObservations
from rfm_core.settings import setting

__all__ = ['DetectorInput', 'DetectorConfig', 'Detector', 'finalize', 'no_detections']


@dataclass
class DetectorInput:
    """One frame for a detector. Arrays are (H, W[, 3]); depth in metres, NaN = missing."""

    stamp_ns: int
    frame_id: str
    intrinsics: CameraIntrinsics
    gravity_cam: np.ndarray               #: unit "down" in the camera optical frame
    rgb: np.ndarray | None = None         #: (H, W, 3) uint8
    depth: np.ndarray | None = None       #: (H, W) float32 metres, aligned to rgb

    def validate(self, needs_depth: bool) -> None:
        """Raise ValueError saying what is wrong with this input."""
        h, w = self.intrinsics.height, self.intrinsics.width
        if self.rgb is not None and self.rgb.shape[:2] != (h, w):
            raise ValueError(f'image is {self.rgb.shape[1]}x{self.rgb.shape[0]} but camera_info '
                             f'says {w}x{h}')
        if needs_depth:
            if self.depth is None:
                raise ValueError('this backend needs a depth image (depth/image)')
            if self.depth.shape != (h, w):
                raise ValueError(f'depth is {self.depth.shape[1]}x{self.depth.shape[0]} but '
                                 f'camera_info says {w}x{h}; depth must be registered to colour')
            if not np.any(np.isfinite(self.depth)):
                raise ValueError('depth image has no valid pixels')


@dataclass(frozen=True)
class DetectorConfig:
    """Settings common to every backend (paper defaults)."""

    score_threshold: float = setting(0.25, 'Keep detections scoring at least this', lo=0.0, hi=1.0,
                                     paper='0.25 on CA-1M')
    max_detections: int = setting(100, 'At most this many detections per frame (the best scores)', lo=1, hi=1000)
    cloud_voxel_m: float = setting(0.12, "Depth points sent with each frame's detections (FrameDetections.cloud, "
                                   'for relative poses and tracking on points): one per cell of this size (m; '
                                   '0: none)', lo=0.0, hi=1.0)
    cloud_max_range_m: float = setting(6.0, '... from depth up to this range (m)', lo=0.5, hi=100.0)
    label_map: str = setting('', "Class names are NYU40's (rfm_core.detection.labels); rename or merge on top: "
                             "'FROM:TO' entries, comma-separated, FROM a detector class or an NYU40 name (e.g. "
                             "'monitor:monitor,otherprop:clutter')", read_only=True)

    def __post_init__(self):
        label_map(self.label_map)            # a wrong entry fails at start-up, saying which


class Detector:
    """Base class: ``detect(frame) -> FrameObservations``."""

    name = 'base'
    needs_depth = False
    monocular = False    #: distances judged from RGB alone: errors run along the viewing rays

    def detect(self, frame: DetectorInput) -> FrameObservations:  # pragma: no cover
        raise NotImplementedError

    def points_only(self, frame: DetectorInput) -> FrameObservations:
        """The frame without detections: its stamp, gravity and depth points (``cloud``), for
        a frame the detector is behind on (the matcher tracks it on the points)."""
        frame.validate(needs_depth=True)
        return no_detections(frame, self.config, self.name)


def no_detections(frame: DetectorInput, config: DetectorConfig, backend: str) -> FrameObservations:
    """The frame without detections: its stamp, gravity and (where it has depth) its depth
    points."""
    return finalize(frame, np.zeros((0, 7)), np.zeros(0), [], np.zeros((0, 0), np.float32), np.zeros((0, 4)),
                    config, backend)


def finalize(frame: DetectorInput, boxes, scores, labels, embeddings, boxes_2d, config: DetectorConfig,
             backend: str, visibility=None, object_ids=None, full_boxes=None,
             camera_height: float = float('nan'), walls=None) -> FrameObservations:
    """Threshold by score, keep the best ``max_detections``, name the classes (NYU40's and
    ``label_map``'s), package as FrameObservations (``full_boxes``, ``camera_height``,
    ``walls``: see :class:`FrameObservations`; the frame's depth points as ``cloud`` where it
    has depth)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    scores = np.asarray(scores, dtype=np.float32).reshape(-1)
    keep = np.flatnonzero(scores >= config.score_threshold)
    keep = keep[np.argsort(-scores[keep], kind='stable')][:config.max_detections]
    embeddings = np.asarray(embeddings, dtype=np.float32)
    n = len(boxes)
    return FrameObservations(
        stamp_ns=frame.stamp_ns, frame_id=frame.frame_id, intrinsics=frame.intrinsics,
        gravity_cam=frame.gravity_cam, boxes=boxes[keep], scores=scores[keep],
        labels=label_map(config.label_map).names([labels[i] for i in keep]),
        embeddings=embeddings.reshape(n, -1)[keep] if n else np.zeros((0, 0), np.float32),
        boxes_2d=np.asarray(boxes_2d, dtype=np.float32).reshape(-1, 4)[keep],
        visibility=(np.asarray(visibility, np.float32)[keep] if visibility is not None
                    else np.full(len(keep), -1.0, np.float32)),
        object_ids=(np.asarray(object_ids, np.int64)[keep] if object_ids is not None
                    else np.full(len(keep), -1, np.int64)),
        full_boxes=np.asarray(full_boxes, np.float64).reshape(-1, 7)[keep] if full_boxes is not None else None,
        backend=backend, camera_height=camera_height,
        walls=np.zeros((0, 3)) if walls is None else np.asarray(walls, np.float64).reshape(-1, 3),
        cloud=depth_cloud(frame.depth, frame.intrinsics, frame.gravity_cam, config.cloud_voxel_m,
                          config.cloud_max_range_m))
