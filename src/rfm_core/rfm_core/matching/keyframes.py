"""Keyframes (paper 3.2-3.4, made live): when a frame becomes one, and what a new keyframe is
matched against.

A frame becomes a keyframe when tracking fails, or when it shares too few objects with the
reference keyframe, or has moved or turned too far from it (:func:`is_keyframe`). A new
keyframe is matched against candidates (:meth:`NewKeyframe.candidates`): the few most
recent keyframes plus the keyframes whose bag-of-objects descriptor is most similar, so the
cost per keyframe stays bounded however large the map grows. Within a stream segment a
relative pose resting on two objects is kept towards a recent keyframe (the motion prior has
checked it); across segments every edge needs ``min_retrieved_inliers`` verified objects
(two verify nothing beyond the minimal sample, and repeated furniture aliases), and a
keyframe that starts a segment retrieves ``unordered_retrieved_keyframes`` candidates. A
keyframe of a stream that verifies nothing is placed by the motion alone for a moment
(:meth:`NewKeyframe.motion_edge`). Where tracking failed, the previous frame, tracked
moments earlier, can become the keyframe instead (:class:`Bridge`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rfm_core.geometry import Pose4, yaw_matrix
from rfm_core.matching.graph import (IDENTITY, Edge, Frame, GraphStep, Keyframe, TrackState, bag_of_objects, tracked,
                                     without_objects)
from rfm_core.matching.relative_pose import RelativePose, with_surfaces
from rfm_core.observations import FrameObservations, FrameTrack
from rfm_core.settings import constant, setting

if TYPE_CHECKING:
    from rfm_core.matching.view_graph import ViewGraphBuilder

__all__ = ['KeyframeConfig', 'is_keyframe', 'weak', 'Bridge', 'NewKeyframe']


@dataclass(frozen=True)
class KeyframeConfig:
    min_overlap: float = setting(0.3, 'A frame becomes a keyframe when fewer than this share of its objects match '
                                 'the reference keyframe ...', lo=0.0, hi=1.0)
    max_translation_m: float = setting(0.5, '... or it has moved this far from it (m) ...', lo=0.0, hi=100.0)
    max_yaw_deg: float = setting(20.0, '... or turned this far (deg)', lo=0.0, hi=180.0)
    min_detections: int = setting(2, 'Frames with fewer detections are tracked on their depth points only',
                                  lo=0, hi=1000)
    min_keyframe_detections: int = constant(3, 'Within a stream, a frame with fewer detections becomes no keyframe '
                                            'where a neighbour of the reference already covers its predicted pose',
                                            lo=0, hi=1000)
    recent_keyframes: int = setting(3, 'A new keyframe is matched against this many latest keyframes ...',
                                    lo=0, hi=100)
    retrieved_keyframes: int = setting(5, '... and this many older ones most similar by bag of objects',
                                       lo=0, hi=100)
    unordered_retrieved_keyframes: int = constant(15, 'Retrieved keyframes for a keyframe that starts a stream '
                                                  'segment (a separate view)', lo=0, hi=100)
    min_retrieval_similarity: float = constant(0.3, 'Least bag-of-objects similarity of a retrieved keyframe',
                                               lo=0.0, hi=1.0)
    min_retrieved_inliers: int = setting(3, 'Verified objects an edge needs where the motion prior cannot check '
                                         'it (separate views, retrieved keyframes)', lo=2, hi=100)
    max_motion_edge_s: float = constant(1.0, "A keyframe that verified nothing is placed by the gyroscope's yaw and "
                                        'the predicted position at most this long after the last frame objects '
                                        'placed (s; 0: never)', lo=0.0, hi=60.0)


def is_keyframe(g: 'ViewGraphBuilder', obs: FrameObservations, rel: RelativePose | None,
                reference: FrameObservations | None = None) -> bool:
    """Whether a frame becomes a keyframe, given its verified pose ``rel`` to the reference
    keyframe (or to ``reference``)."""
    if not g.keyframes or rel is None:
        return True
    cfg = g.config.keyframes
    last = reference if reference is not None else g.reference.observations
    overlap = len(rel.inliers) / max(min(len(obs), len(last)), 1)
    return (overlap < cfg.min_overlap
            or np.linalg.norm(rel.pose.t) > cfg.max_translation_m
            or np.degrees(abs(rel.pose.yaw)) > cfg.max_yaw_deg)


def weak(g: 'ViewGraphBuilder', obs: FrameObservations, stream: bool, pose: Pose4 | None = None) -> bool:
    """Whether a frame of a stream has too few detections to become a new keyframe where the
    map already has one: a neighbour of the reference (not the reference itself, which it
    failed to track against) within ``max_translation_m`` and ``max_yaw_deg`` of its pose
    relative to the reference (``pose``, else predicted). It could not verify a revisit and
    its edges would rest on two objects: on a long capture such views would add keyframes
    with time, not with the room."""
    cfg = g.config.keyframes
    if not (stream and g.keyframes and len(obs) < cfg.min_keyframe_detections):
        return False
    pose = pose if pose is not None else g.predicted_pose(obs)        # T_ref_frame
    if pose is None:
        return False
    ref = g.ref % len(g.keyframes)
    for j in g.neighbours.get(ref, ()):
        if (g.edge_pose[ref, j].inverse() @ pose).within(cfg.max_translation_m, cfg.max_yaw_deg):  # T_j_frame
            return True
    return False


class NewKeyframe:
    """The frame becomes a keyframe, with its verified edges to the candidates."""

    def __init__(self, g: 'ViewGraphBuilder'):
        self.g = g

    def candidates(self, descriptor: np.ndarray, separate: bool = False) -> list:
        """Indices of keyframes to match a new keyframe against (bounded in number);
        ``separate``: the keyframe starts a stream segment (more are retrieved)."""
        g, cfg = self.g, self.g.config.keyframes
        n = len(g.keyframes)
        recent = list(range(max(0, n - cfg.recent_keyframes), n))
        older = n - len(recent)
        if n and g.ref % n not in recent:                 # the reference (a revisited keyframe)
            recent.append(g.ref % n)
        wanted = cfg.unordered_retrieved_keyframes if separate else cfg.retrieved_keyframes
        if older > 0 and wanted > 0 and g.descriptors.shape[1] == len(descriptor):
            sims = g.descriptors[:older] @ descriptor
            k = min(wanted, older)
            top = np.argpartition(-sims, k - 1)[:k]
            top = top[np.argsort(-sims[top])]
            recent += [int(i) for i in top if sims[i] >= cfg.min_retrieval_similarity and int(i) not in recent]
        return recent

    def motion_edge(self, obs: FrameObservations) -> RelativePose | None:
        """Where the camera went while tracking was lost for a moment: the reference to this
        frame as the gyroscope's yaw and the last tracked frame's position, moved on at the
        camera's recent velocity, predict it, refined on the two frames' surfaces. Where the
        depth points fix every direction (``rel.on_points``) or a robot's odometry measured the
        motion it is a measurement; otherwise at most ``max_motion_edge_s`` after the last
        frame that objects (or points) placed: motion edges never chain longer. It has no
        object matches; the averaging weighs it as ``averaging.points_edge_weight`` objects.
        A robot's keyframe gets it from the reference whenever objects did not link the two,
        beside the edges objects gave from older keyframes."""
        g = self.g
        predicted = g.predicted_pose(obs)
        if predicted is None:
            return None
        rel = with_surfaces(without_objects(predicted), g.reference.observations, obs, g.matching)
        # guessed from the last frame objects placed, motion edges never chain past it; a
        # robot's odometry measures the motion, which the gyroscope and the velocity guess
        if (not rel.on_points and g.motion.carried(g.state, g.reference, obs) is None
                and obs.stamp_ns - g.state.last_verified_ns > g.config.keyframes.max_motion_edge_s * 1e9):
            return None
        g.stats.motion_edges += 1
        return rel

    def __call__(self, frame: Frame) -> GraphStep:
        g, obs, stream, last_rel = self.g, frame.obs, frame.stream, frame.last_rel
        cfg = g.config.keyframes
        start = time.perf_counter()
        descriptor = bag_of_objects(obs)
        keyframe = Keyframe(g.next_id, obs, descriptor, g.motion.segment)
        g.next_id += 1
        edges = []
        cand = self.candidates(descriptor, separate=not stream)
        g.stats.last_candidates = [g.keyframes[i].keyframe_id for i in cand]
        last = g.ref % len(g.keyframes) if g.keyframes else -1      # the reference: last_rel's
        # two verified objects suffice for a recent neighbour of the same stream segment,
        # where the motion prior has checked the pose
        recent_from = len(g.keyframes) - cfg.recent_keyframes
        others = [i for i in cand if i != last]            # matched in one batch
        batched = dict(zip(others, g.matcher.match_many(obs, [g.keyframes[i].observations for i in others])))
        for i in cand:
            source = g.keyframes[i]
            same = source.segment == keyframe.segment
            g.stats.pairs_tested += 1
            if i == last:
                rel = last_rel
            else:
                rel = g.relative(source.observations, obs, batched[i], stream=same)
                if same:
                    rel = g.motion.plausible(rel, source.observations, obs)
            if rel is not None and ((same and (i >= recent_from or i == last))
                                    or len(rel.inliers) >= cfg.min_retrieved_inliers):
                edges.append(Edge(source.keyframe_id, keyframe.keyframe_id, rel))
        # no edge from the reference the stream was tracked on: its motion edge, alone, or on
        # a robot beside the edges objects of older keyframes gave (the odometry still
        # measures that link, which outvotes a look-alike match of two objects among them)
        if (stream and g.keyframes and not any(e.source_id == g.reference.keyframe_id for e in edges)
                and (not edges or g.motion.carried(g.state, g.reference, obs) is not None)):
            motion = self.motion_edge(obs)
            if motion is not None and not edges:
                if not motion.on_points:                           # placed by the motion alone
                    g.motion_placed.add(keyframe.keyframe_id)
                # the camera keeps its velocity through the new keyframe (a vector: rotated only)
                g.motion.carry(keyframe.keyframe_id, yaw_matrix(motion.pose.yaw).T @ g.motion.velocity(g.state))
            if motion is not None:
                edges.append(Edge(g.reference.keyframe_id, keyframe.keyframe_id, motion))
        g.add_keyframe(keyframe, edges)
        g.stats.keyframes += 1
        g.stats.tracked += 1
        g.stats.edges += len(edges)
        g.stats.keyframe_s += time.perf_counter() - start
        g.state = TrackState(keyframe.keyframe_id, IDENTITY, obs.stamp_ns, None,
                             verified_ns=g.verified_through(keyframe.keyframe_id))
        return GraphStep(keyframe, edges, FrameTrack(
            obs.stamp_ns, obs.frame_id, obs.gravity_cam, keyframe.keyframe_id, obs.stamp_ns, IDENTITY, 0,
            is_keyframe=True, continuous=stream))


class Bridge:
    """Tracking failed against the reference: if the frame verifies against the last frame
    that was tracked (moments earlier), that frame becomes the keyframe (linked to the
    reference by its tracked pose) and this frame is tracked against it."""

    def __init__(self, g: 'ViewGraphBuilder'):
        self.g = g

    def __call__(self, frame: Frame) -> GraphStep | None:
        g, obs, prev = self.g, frame.obs, self.g.state
        if not (frame.stream and prev is not None and prev.observations is not None
                and len(prev.observations) >= g.config.keyframes.min_detections and frame.last_rel is None):
            return None
        if prev.keyframe_id == g.reference.keyframe_id and weak(g, prev.observations, True, prev.pose):
            return None
        start = time.perf_counter()
        rel = g.motion.plausible(g.relative(prev.observations, obs, stream=True), prev.observations, obs)
        g.stats.tracking_s += time.perf_counter() - start
        if rel is None:
            return None
        # the previous frame becomes a keyframe, linked by its tracked pose
        step = g.new_keyframe(Frame(prev.observations, True, prev.relative))
        keyframe = step.keyframe
        g.state = TrackState(keyframe.keyframe_id, rel.pose, obs.stamp_ns, obs, rel,
                             verified_ns=g.verified_through(keyframe.keyframe_id))
        g.stats.bridged += 1
        return GraphStep(keyframe, step.edges, tracked(frame, keyframe, rel.pose, len(rel.inliers), continuous=True))
