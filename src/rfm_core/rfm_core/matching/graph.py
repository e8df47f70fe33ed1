"""The view graph's data: keyframes, verified edges, what a frame did, and the state the
localizers share (:mod:`rfm_core.matching.view_graph` runs them)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from rfm_core.geometry import Pose4
from rfm_core.matching.relative_pose import RelativePose
from rfm_core.observations import FrameObservations, FrameTrack

__all__ = ['Keyframe', 'Edge', 'GraphStep', 'Frame', 'TrackState', 'GraphStats', 'bag_of_objects', 'reversed_pose',
           'without_objects', 'tracked', 'IDENTITY']

IDENTITY = Pose4(0.0, (0.0, 0.0, 0.0))


@dataclass
class Keyframe:
    keyframe_id: int
    observations: FrameObservations
    descriptor: np.ndarray            #: unit bag-of-objects descriptor (D,)
    segment: int = 0                  #: stream segment (frames no more than max_frame_gap_s apart)


@dataclass
class Edge:
    """A verified relative pose: ``relative.pose`` is T_source_target (maps the target
    keyframe's gravity-aligned frame into the source's), ``relative.inliers`` are
    (source detection, target detection) index pairs."""

    source_id: int
    target_id: int
    relative: RelativePose

    @property
    def score(self) -> float:
        """Confidence in [0, 1]: the share of matched objects that verified the pose."""
        return float(np.clip(self.relative.inlier_ratio, 0.0, 1.0))


class GraphStep(NamedTuple):
    """What one frame did to the view graph: the keyframe it became (or None), the edges it
    added (a new keyframe's, or those a revisiting frame measured), and the frame's pose
    relative to a keyframe (None when it could not be localized)."""

    keyframe: Keyframe | None
    edges: list
    track: FrameTrack | None


@dataclass
class Frame:
    """A frame on its way through the localizers."""

    obs: FrameObservations
    stream: bool                      #: it continues the stream of the previous frame
    last_rel: RelativePose | None = None   #: its verified pose to the reference (tracking), once tried


@dataclass
class TrackState:
    """The last frame localized (or keyframe made), which predicts the next."""

    keyframe_id: int                  #: the keyframe the frame was localized against
    pose: Pose4                       #: T_keyframe_frame of that frame
    stamp_ns: int
    observations: FrameObservations | None = None   #: that frame (None: it is the keyframe)
    relative: RelativePose | None = None            #: its verified pose to the keyframe
    verified_ns: int | None = None    #: stamp of the last frame placed by objects (None: this one)

    @property
    def last_verified_ns(self) -> int:
        return self.stamp_ns if self.verified_ns is None else self.verified_ns


@dataclass
class GraphStats:
    frames: int = 0
    skipped: int = 0
    tracked: int = 0                  #: frames localized against a keyframe (keyframes included)
    segments: int = 0                 #: stream segments begun (separate views each begin one)
    bridged: int = 0                  #: lost frames tracked through the previous frame made keyframe
    keyframes: int = 0
    pairs_tested: int = 0
    edges: int = 0
    implausible: int = 0
    imu_rejected: int = 0             #: relative poses whose yaw the gyroscope contradicted
    predicted_tracking: int = 0       #: frames tracked with predicted matches (no object matcher)
    point_tracked: int = 0            #: frames tracked on their depth points alone (objects did not place them)
    odometry_tracked: int = 0         #: frames a robot's odometry placed (neither objects nor points did)
    odometry_rejected: int = 0        #: relative poses a robot's odometry contradicted
    motion_edges: int = 0             #: keyframes placed by the motion alone (tracking lost a moment)
    reused: int = 0                   #: frames that made an older keyframe the reference (revisits)
    reused_on_points: int = 0         #: ... of them aligned to it on their depth points (objects did not verify)
    handovers: int = 0                #: edges from the reference left to the keyframe revisited
    through: int = 0                  #: edges between keyframes measured through a revisiting frame
    last_candidates: list = field(default_factory=list)
    tracking_s: float = 0.0           #: time spent localizing frames against keyframes
    keyframe_s: float = 0.0           #: time spent matching new keyframes against candidates


def bag_of_objects(obs: FrameObservations) -> np.ndarray:
    """Retrieval descriptor of a frame: the unit mean of its object embeddings (zeros when
    it has none)."""
    if obs.embeddings.shape[1] == 0 or len(obs) == 0:
        return np.zeros(max(obs.embeddings.shape[1], 1))
    v = obs.embeddings.astype(np.float64).mean(0)
    return v / max(np.linalg.norm(v), 1e-9)


def reversed_pose(rel: RelativePose) -> RelativePose:
    """T_b_a of a verified T_a_b, its inliers as (b, a)."""
    return RelativePose(rel.pose.inverse(), rel.inliers[:, ::-1], rel.inlier_ious, rel.inlier_scores,
                        rel.mean_error, rel.num_matches)


def without_objects(pose: Pose4) -> RelativePose:
    """A relative pose no object match supports (the motion's, or the depth points'): it weighs
    ``averaging.points_edge_weight`` in the averaging."""
    return RelativePose(pose, np.zeros((0, 2), int), np.zeros(0), np.zeros(0), mean_error=1.0, num_matches=0)


def tracked(frame: Frame, keyframe: Keyframe, pose: Pose4, inliers: int, continuous: bool | None = None) -> FrameTrack:
    """The frame's track: ``pose`` (T_keyframe_frame) against ``keyframe`` on ``inliers``
    verified objects (0: its depth points placed it); ``continuous`` defaults to whether it
    continues the stream."""
    obs = frame.obs
    return FrameTrack(obs.stamp_ns, obs.frame_id, obs.gravity_cam, keyframe.keyframe_id,
                      keyframe.observations.stamp_ns, pose, inliers, is_keyframe=False,
                      continuous=frame.stream if continuous is None else continuous)
