"""Tracking (paper 3.4, made live): each frame localized against the reference keyframe.

:class:`Tracking`: the frame's verified relative pose to the reference localizes it, decides
whether it becomes a keyframe, and is reused as that keyframe's edge to the reference. In a
stream the boxes are first matched where the previous frame's pose, the camera's velocity
and the gyroscope predict them, and the object matcher is asked only when that does not
verify; the motion from the previous tracked frame must be plausible. Across a gap the pose
needs ``min_retrieved_inliers`` objects.

:class:`PointTracking` (not in the paper): a frame of a stream that objects do not localize
(too few detections, tracking failed, or a frame the detector sent with its depth points
only) is aligned on its depth points to the reference keyframe's from the predicted pose
(:func:`rfm_core.matching.relative_pose.track_on_points`); it becomes no keyframe.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import linear_sum_assignment

from rfm_core.geometry import Pose4
from rfm_core.matching.classical import ObjectMatches
from rfm_core.matching.graph import Frame, GraphStep, TrackState, tracked
from rfm_core.matching.keyframes import is_keyframe, weak
from rfm_core.matching.relative_pose import RelativePose, track_on_points
from rfm_core.observations import FrameObservations
from rfm_core.settings import constant

if TYPE_CHECKING:
    from rfm_core.matching.view_graph import ViewGraphBuilder

__all__ = ['TrackingConfig', 'Tracking', 'PointTracking']


@dataclass(frozen=True)
class TrackingConfig:
    track_gate_m: float = constant(0.3, "A box matches the reference's box predicted nearest within this (m) plus "
                                   'the distance the camera can have moved', lo=0.01, hi=5.0)


class Tracking:
    """The frame against the reference keyframe (see the module): its track when it stays a
    frame; otherwise None, with its verified pose to the reference kept in ``frame.last_rel``
    for the localizers after it."""

    def __init__(self, g: 'ViewGraphBuilder'):
        self.g = g

    def __call__(self, frame: Frame) -> GraphStep | None:
        g, obs = self.g, frame.obs
        start = time.perf_counter()
        frame.last_rel = self.relative_pose(obs, frame.stream) if g.keyframes else None
        g.stats.tracking_s += time.perf_counter() - start
        rel = frame.last_rel
        if rel is None or not (weak(g, obs, frame.stream) or not is_keyframe(g, obs, rel)):
            return None
        ref = g.reference
        g.state = TrackState(ref.keyframe_id, rel.pose, obs.stamp_ns, obs, rel,
                             verified_ns=g.verified_through(ref.keyframe_id))
        g.stats.tracked += 1
        return GraphStep(None, [], tracked(frame, ref, rel.pose, len(rel.inliers)))

    def predicted_matches(self, keyframe: FrameObservations, obs: FrameObservations,
                          predicted: Pose4 | None) -> ObjectMatches | None:
        """Matches of the frame's boxes to the reference's where the predicted pose
        (T_keyframe_frame) puts them (nearest centre, one-to-one, within the distance the
        camera can have moved plus the detector's noise): tracking without the object
        matcher. None when nothing predicts the pose."""
        g = self.g
        if predicted is None or len(obs) == 0 or len(keyframe) == 0:
            return None
        moved = predicted.transform_points(obs.boxes[:, :3])          # frame boxes in the keyframe
        d = np.linalg.norm(moved[:, None, :] - keyframe.boxes[None, :, :3], axis=-1)
        dt = abs(obs.stamp_ns - g.state.stamp_ns) / 1e9
        gate = g.config.tracking.track_gate_m + g.config.motion.max_speed_m_s * dt
        rows, cols = linear_sum_assignment(np.where(d < gate, d, 1e3))
        keep = d[rows, cols] < gate
        rows, cols = rows[keep], cols[keep]
        return ObjectMatches(rows, cols, 1.0 - d[rows, cols] / gate)

    def relative_pose(self, obs: FrameObservations, stream: bool) -> RelativePose | None:
        """The frame's verified pose relative to the reference, or None (see the module)."""
        g = self.g
        last = g.reference
        rel = None
        pose = g.predicted_pose(obs) if stream else None
        predicted = self.predicted_matches(last.observations, obs, pose)
        if predicted is not None and len(predicted) >= 2:
            rel = g.relative(last.observations, obs, predicted, stream=stream, predicted=pose)
            if rel is not None and len(rel.inliers) < max(2, 0.5 * len(predicted)):
                rel = None
            g.stats.predicted_tracking += rel is not None
        if rel is None:
            rel = g.relative(last.observations, obs, stream=stream, predicted=pose)
        if rel is None:
            return None
        if not stream:
            return rel if len(rel.inliers) >= g.config.keyframes.min_retrieved_inliers else None
        prev = g.state
        if prev is not None and prev.keyframe_id == last.keyframe_id:
            # T_prev_frame = T_kf_prev^-1 T_kf_frame, over the time since the previous frame
            ok = g.motion.reachable(prev.pose.inverse() @ rel.pose, prev.stamp_ns, obs.stamp_ns)
        else:
            ok = g.motion.reachable(rel.pose, last.observations.stamp_ns, obs.stamp_ns)
        if not (ok and g.motion.sensors_agree(rel.pose, last.observations, obs)):
            return None
        return g.motion.with_odometry(rel, prev, last, obs, g.config.keyframes.min_retrieved_inliers)


class PointTracking:
    """A frame of a stream that objects did not localize, tracked on its depth points:
    aligned to the reference keyframe's from the predicted pose, where the motion is
    plausible; None otherwise. The directions the points leave free (at most
    ``matching.point_track_max_free``: a wall alone fixes only the distance to it and the yaw)
    keep the prediction, and only within ``max_motion_edge_s`` of the last frame placed in full. Where
    the points place nothing, a robot's odometry carries the frame on from the last one
    (:meth:`~rfm_core.matching.motion.StreamMotion.carried`). The frame becomes no
    keyframe; a bridge from it to a later frame weighs its pose as a motion edge (no object
    matches)."""

    def __init__(self, g: 'ViewGraphBuilder'):
        self.g = g

    def __call__(self, frame: Frame) -> GraphStep | None:
        g, obs, prev = self.g, frame.obs, self.g.state
        if not (frame.stream and g.keyframes and prev is not None):
            return None
        ref = g.reference
        odometry = g.motion.carried(prev, ref, obs)               # a robot's, where it has odometry
        predicted = odometry if odometry is not None else g.predicted_pose(obs)      # T_ref_frame
        if predicted is None:
            return None
        start = time.perf_counter()
        found = track_on_points(predicted, ref.observations, obs, g.matching)
        g.stats.tracking_s += time.perf_counter() - start
        full = found is not None and found.free == 0
        late = obs.stamp_ns - prev.last_verified_ns > g.config.keyframes.max_motion_edge_s * 1e9
        if (found is None or found.free > g.matching.point_track_max_free or not full and late and odometry is None
                or not (g.motion.reachable(prev.pose.inverse() @ found.pose, prev.stamp_ns, obs.stamp_ns)
                        and g.motion.sensors_agree(found.pose, ref.observations, obs))):
            if odometry is None:
                return None
            g.stats.odometry_tracked += 1                         # the robot's odometry carries it
            return g.placed_on_points(frame, ref, odometry, prev.last_verified_ns)
        g.stats.point_tracked += 1
        verified_ns = g.verified_through(ref.keyframe_id) if full else prev.last_verified_ns
        return g.placed_on_points(frame, ref, found.pose, verified_ns)
