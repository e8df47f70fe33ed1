"""The whole back end on a simulated capture, in-process: detector -> view graph ->
mapper, then the paper's localization and mapping metrics.

Ground truth stays out of the pipeline's inputs: detections come from a backend (the
``ground_truth`` backend perturbs the visible boxes by its noise model and hides object
ids from everything but the evaluation), gravity and the gyroscope's orientation are the
frame's true ones (the IMU filter's job, evaluated separately), and poses are used only in
``posed`` mode (the paper's posed rows) and for scoring.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from rfm_core.evaluation.mapping import evaluate_map
from rfm_core.evaluation.report import GroundTruth, frames_seeing_mapped, map_boxes
from rfm_core.evaluation.trajectory import map_to_truth, trajectory_errors
from rfm_core.geometry import Pose4
from rfm_core.mapping.localization import StreamLocalizer
from rfm_core.mapping.mapper import Mapper, MapperConfig
from rfm_core.matching.config import monocular
from rfm_core.matching.view_graph import ViewGraphConfig
from rfm_core.session import Session
from rfm_core.sim.capture import Capture, CaptureConfig

__all__ = ['PipelineResult', 'run_capture', 'detections_for', 'relocalize_capture']


@dataclass
class PipelineResult:
    localization: dict                      #: ATE/ARE median + RMSE (m, deg), registered share
    mapping: dict                           #: AP15, AR15, AP25, AR25, objects, ground_truth
    keyframes: int
    frames: int
    seconds: dict = field(default_factory=dict)   #: per stage
    mapper: Mapper | None = None
    truth: dict = field(default_factory=dict)     #: keyframe id -> 4x4 true camera-to-world
    alignment: object = None                      #: Pose4 T_world_map used for scoring


def detections_for(spec: str, noise_seed: int = 0):
    """A function SimFrame -> FrameObservations for a detector spec ('depth_clusters',
    'ground_truth:rgbd', ...). Object ids are stripped (the pipeline must not see them). The
    function's ``monocular`` attribute is the detector's."""
    from rfm_core.detection import detector_for_spec  # noqa: PLC0415

    det = detector_for_spec(spec, noise_seed)
    if det.name == 'ground_truth':
        def run(frame):
            obs = det.perturb(frame.ground_truth)
            return replace(obs, object_ids=np.full(len(obs), -1, np.int64), visibility=np.full(len(obs), -1.0))
    else:
        def run(frame):
            return det.detect(frame.detector_input())
    run.monocular = det.monocular
    return run


def run_capture(config: CaptureConfig, detector: str = 'ground_truth:rgbd', matcher=None,
                posed: bool = False, bundle_adjustment: bool = False, noise_seed: int = 0, mapper_config: MapperConfig | None = None,
                graph_config: ViewGraphConfig | None = None, min_visibility: float = 0.2,
                capture: Capture | None = None, frames=None) -> PipelineResult:
    """Run detector -> view graph -> mapper over a capture and score it. ``capture`` and
    ``frames`` (its rendered SimFrames) may be passed in to reuse one rendering."""
    capture = capture or Capture(config)
    detect = detections_for(detector, noise_seed)
    mcfg = mapper_config or MapperConfig()
    mcfg = replace(mcfg, posed=posed or mcfg.posed,
                   bundle_adjustment=bundle_adjustment or mcfg.bundle_adjustment,
                   matching=monocular(mcfg.matching) if detect.monocular else mcfg.matching)
    truth, frame_truth, aligned_truth, detect_s = {}, {}, {}, 0.0
    session = Session(mcfg, graph_config, matcher=matcher,
                      pose_lookup=(lambda obs: aligned_truth[obs.stamp_ns]) if posed else None)
    mapper = session.mapper
    best_visibility = np.zeros(len(capture.room.objects))
    n_frames = 0
    for frame in (frames if frames is not None else capture.frames()):
        n_frames += 1
        gt = frame.ground_truth
        np.maximum.at(best_visibility, gt.object_ids - 1, gt.visibility)
        t0 = time.perf_counter()
        obs = detect(frame)
        # the gyroscope's orientation, as the detector node attaches it (here: the true one)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1
        detect_s += time.perf_counter() - t0
        frame_truth[frame.stamp_ns] = frame.pose_matrix
        aligned_truth[frame.stamp_ns] = frame.aligned_from_map()
        step = session.step(obs)
        if step.keyframe is not None:             # (this frame or, bridging lost tracking, an earlier one)
            truth[step.keyframe.keyframe_id] = frame_truth[step.keyframe.observations.stamp_ns]
    tracks = session.finish()
    times = {'detect': detect_s, **session.seconds}
    # every frame of the capture counts (the paper's registration); keyframes beside it
    estimated = mapper.frame_poses()
    loc = trajectory_errors(estimated, frame_truth, align=False if posed else '4dof')
    # keyframes culled from the map count with their own frame's pose (through the keyframe that holds them)
    keyframe_poses = mapper.camera_poses()
    keyframe_poses.update({k: estimated[m.stamp_ns] for k, m in mapper.merged.items() if m.stamp_ns in estimated})
    kf = trajectory_errors(keyframe_poses, truth, align=False if posed else '4dof')
    loc.update({f'keyframe_{k}': v for k, v in kf.items()})
    # express the map in the world frame: identity when posed, else the 4-DoF alignment
    align = Pose4(0.0, (0, 0, 0)) if posed else map_to_truth(estimated, frame_truth)
    boxes = map_boxes(tracks, align)
    scores = np.array([t.score for t in tracks])
    mapping = evaluate_map(boxes, scores, capture.room.boxes, best_visibility < min_visibility,
                           labels=[t.label for t in tracks], gt_labels=capture.room.labels)
    return PipelineResult(loc, mapping, len(truth), n_frames, times, mapper, truth, align)


def relocalize_capture(mapper: Mapper, map_to_world: Pose4, capture: Capture, detector: str,
                       noise_seed: int = 0) -> dict:
    """Localize the frames of ``capture`` against ``mapper``'s map (paper appendix) as
    localization mode does (:class:`~rfm_core.mapping.localization.StreamLocalizer`; each
    frame alone with ``relocalization.stream`` off) and score the poses in the world frame
    (``map_to_world``: T_world_map, e.g. from
    :func:`rfm_core.evaluation.trajectory.map_to_truth`); frames that fail count as not
    registered. ``wrong``: share of the relocalized frames off by > 5 deg or > 25 cm;
    ``latency_ms``: the median wall time of one query; ``seeing_mapped`` the frames that see two
    objects of the map (:func:`rfm_core.evaluation.report.frames_seeing_mapped`) and
    ``registered_seeing`` the share of them relocalized."""
    detect = detections_for(detector, noise_seed)
    world = map_to_world.matrix()
    relocalized, truth, seconds, index_of = {}, {}, [], {}
    room = GroundTruth(boxes=capture.room.boxes, ids=np.arange(1, len(capture.room.boxes) + 1))
    stream = StreamLocalizer(mapper)
    for frame in capture.frames():
        obs = detect(frame)
        obs.imu_rotation, obs.imu_epoch = frame.rotation, 1      # the gyroscope's, as in run_capture
        truth[frame.index] = frame.pose_matrix
        index_of[obs.stamp_ns] = frame.index
        gt = frame.ground_truth
        room.frame_visibility[frame.index] = dict(zip(gt.object_ids.tolist(), gt.visibility.tolist()))
        start = time.perf_counter()
        placed = stream.step(obs)
        seconds.append(time.perf_counter() - start)
        for o, reloc in placed:
            relocalized[index_of[o.stamp_ns]] = world @ reloc.camera_to_map(o)
    seeing = frames_seeing_mapped(room, map_boxes(mapper.tracks(), map_to_world))
    return {**trajectory_errors(relocalized, truth, align=False),
            'latency_ms': 1e3 * float(np.median(seconds)) if seconds else float('nan'), 'seeing_mapped': len(seeing),
            'registered_seeing': len(seeing & set(relocalized)) / len(seeing) if seeing else float('nan')}
