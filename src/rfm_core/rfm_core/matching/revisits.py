"""Revisits (not in the paper): a frame of a stream that would become a keyframe is first
localized against older keyframes, so that the map grows with the places seen, not with time.

:class:`Revisit`: against the reference's neighbourhood in the graph and the retrieved
keyframes, by its objects; one that verifies it becomes the reference instead of a new
keyframe, and the frame sends the edges a keyframe there would have added, measured through
itself, so that a map that stops growing still gets the repeated measurements that outvote
a wrong edge. :class:`RevisitOnPoints`: where its objects verify no older keyframe, its
depth points may: the view graph's own edges put older keyframes near it, and one whose
surfaces it aligns to becomes the reference all the same (no edge: nothing verified the
objects), so that the same place seen again adds no keyframe.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rfm_core.geometry import Pose4
from rfm_core.matching.graph import (IDENTITY, Edge, Frame, GraphStep, TrackState, bag_of_objects, reversed_pose,
                                     tracked)
from rfm_core.matching.keyframes import is_keyframe
from rfm_core.matching.relative_pose import RelativePose, track_on_points
from rfm_core.settings import constant

if TYPE_CHECKING:
    from rfm_core.matching.view_graph import ViewGraphBuilder

__all__ = ['RevisitConfig', 'Revisit', 'RevisitOnPoints']


@dataclass(frozen=True)
class RevisitConfig:
    revisit_edges: int = constant(8, 'Measurements of one keyframe pair that revisiting frames may add (0: none)',
                                  lo=0, hi=16)
    nearest_on_points: int = constant(3, 'Revisits on depth points: the older keyframes nearest the frame that it '
                                      'is aligned to', lo=1, hi=20)


class Revisit:
    """A frame about to become a keyframe, localized against older keyframes instead (the
    reference's neighbours two edges away, then the retrieved ones): of those that verify it
    with ``min_retrieved_inliers`` objects and overlap it as the reference would need, the one
    with the most inliers becomes the reference and the frame is tracked against it, with the
    edges it measured."""

    def __init__(self, g: 'ViewGraphBuilder'):
        self.g = g

    def __call__(self, frame: Frame) -> GraphStep | None:
        g, obs = self.g, frame.obs
        if not (frame.stream and len(g.keyframes) > 1):
            return None
        cfg = g.config.keyframes
        start = time.perf_counter()
        ref = g.ref % len(g.keyframes)
        # the reference's neighbourhood in the graph (two edges away: after one revisit, the
        # keyframes of the earlier pass around it), then the retrieved ones
        near = set(g.neighbours.get(ref, ()))
        near |= {j for i in near for j in g.neighbours.get(i, ())}
        cand = sorted(near - {ref}, reverse=True)[:cfg.retrieved_keyframes + cfg.recent_keyframes]
        cand += [i for i in g.new_keyframe.candidates(bag_of_objects(obs), separate=not frame.stream)
                 if i != ref and i not in cand]
        found, verified = None, []
        if cand:
            matches = g.matcher.match_many(obs, [g.keyframes[i].observations for i in cand])
            for i, m in zip(cand, matches):
                source = g.keyframes[i].observations
                rel = g.relative(source, obs, m, stream=False)
                if rel is None or len(rel.inliers) < cfg.min_retrieved_inliers:
                    continue
                verified.append((i, rel))
                if (not is_keyframe(g, obs, rel, source)
                        and (found is None or len(rel.inliers) > len(found[1].inliers))):
                    found = (i, rel)
        g.stats.tracking_s += time.perf_counter() - start
        return None if found is None else self.revisited(frame, *found, verified)

    def revisited(self, frame: Frame, i: int, rel: RelativePose, verified: list) -> GraphStep:
        """The frame tracked against keyframe index ``i`` (``rel``), which becomes the
        reference, with the edges it measured (at most ``revisit_edges`` of one pair):
        ``frame.last_rel`` its pose to the reference it leaves, ``verified`` the other
        keyframes (index, pose) it verified against."""
        g, obs = self.g, frame.obs
        edges = [self.handover(frame, i, rel)]
        # the frame, as a keyframe would, links the keyframes it verified against: each to the new reference
        edges += [self.through(g.keyframes[i].keyframe_id, g.keyframes[j].keyframe_id,
                               rel.pose @ rel_j.pose.inverse(), [rel, reversed_pose(rel_j)])
                  for j, rel_j in verified if j != i]
        edges = [e for e in edges if e is not None and g.count_pair(e) <= g.config.revisits.revisit_edges]
        g.ref = i
        kf = g.keyframes[i]
        g.state = TrackState(kf.keyframe_id, rel.pose, obs.stamp_ns, obs, rel,
                             verified_ns=g.verified_through(kf.keyframe_id))
        g.stats.tracked += 1
        g.stats.reused += 1
        return GraphStep(None, edges, tracked(frame, kf, rel.pose, len(rel.inliers)))

    def handover(self, frame: Frame, i: int, rel: RelativePose) -> Edge | None:
        """The edge from the reference the frame leaves to keyframe index ``i`` it revisits
        (T_reference_i through the frame: its pose to the reference, ``frame.last_rel`` or
        through the previous tracked frame, and ``rel``, its pose to ``i``), or None. A revisit
        adds no keyframe, but its edge is the measurement a new keyframe would have added."""
        g, obs, last_rel = self.g, frame.obs, frame.last_rel
        ref = g.reference
        legs = []
        if last_rel is not None:
            t_ref_frame = last_rel.pose
            legs.append(last_rel)
        else:
            prev = g.state
            if (prev is None or prev.observations is None or prev.relative is None
                    or prev.keyframe_id != ref.keyframe_id):
                return None
            step = g.motion.plausible(g.relative(prev.observations, obs, stream=True), prev.observations, obs)
            if step is None:
                return None
            t_ref_frame = prev.pose @ step.pose
            legs += [prev.relative, step]
        legs.append(reversed_pose(rel))                                             # (frame, i)
        edge = self.through(ref.keyframe_id, g.keyframes[i].keyframe_id, t_ref_frame @ rel.pose.inverse(), legs)
        g.stats.handovers += edge is not None
        return edge

    def through(self, source_id: int, target_id: int, pose: Pose4, legs: list) -> Edge | None:
        """The edge T_source_target (``pose``) measured through frames: ``legs`` are the
        verified relative poses from the source keyframe to the target one, one after the other;
        its inliers are the objects verified along every leg (None: fewer than two)."""
        chain = {int(a): (int(a), 1.0) for a in legs[0].inliers[:, 0]}
        for leg in legs:
            step_map = {int(a): (int(b), float(s)) for (a, b), s in zip(leg.inliers, leg.inlier_scores)}
            chain = {start: (step_map[end][0], min(score, step_map[end][1]))
                     for start, (end, score) in chain.items() if end in step_map}
        if len(chain) < 2:
            return None
        inliers = np.array([[a, b] for a, (b, _) in chain.items()], int)
        scores = np.array([s for _, s in chain.values()], float)
        ratio = min(leg.inlier_ratio for leg in legs)
        self.g.stats.through += 1
        return Edge(source_id, target_id, RelativePose(
            pose, inliers, np.ones(len(inliers)), scores, max(leg.mean_error for leg in legs),
            max(len(inliers), int(np.ceil(len(inliers) / max(ratio, 1e-3))))))


class RevisitOnPoints:
    """A frame of a stream about to become a keyframe, aligned on its depth points to an older
    keyframe the view graph places near it: of the ``nearest_on_points`` nearest within
    ``max_translation_m`` and ``max_yaw_deg`` of its pose to the reference (``last_rel``, else
    predicted; the newest ``recent_keyframes`` excluded: a revisit, not the walk ahead), the one
    whose surfaces it aligns to in every direction with the most of its points becomes the
    reference, and the frame is tracked against it (no edge: no object verified it); None
    where none aligns."""

    def __init__(self, g: 'ViewGraphBuilder'):
        self.g = g

    def __call__(self, frame: Frame) -> GraphStep | None:
        g, obs, prev = self.g, frame.obs, self.g.state
        if not (frame.stream and len(g.keyframes) > 1):
            return None
        cfg = g.config.keyframes
        pose = frame.last_rel.pose if frame.last_rel is not None else g.predicted_pose(obs)           # T_ref_frame
        if pose is None or prev is None:
            return None
        start = time.perf_counter()
        n = len(g.keyframes)
        skip = set(range(max(0, n - cfg.recent_keyframes), n)) | {g.ref % n}      # the recent ones, the reference
        near = []
        for j, t_ref_j in self.graph_poses().items():
            t_j_frame = t_ref_j.inverse() @ pose
            if j not in skip and t_j_frame.within(cfg.max_translation_m, cfg.max_yaw_deg):
                near.append((float(np.linalg.norm(t_j_frame.t)), j, t_ref_j, t_j_frame))
        ref_id = g.reference.keyframe_id
        found = None
        for _, j, t_ref_j, t_j_frame in sorted(near, key=lambda n: n[0])[:g.config.revisits.nearest_on_points]:
            kf = g.keyframes[j].observations
            a = track_on_points(t_j_frame, kf, obs, g.matching)
            if a is None or a.free or not g.motion.sensors_agree(a.pose, kf, obs):
                continue
            # the motion from the previous frame (on the reference) through the graph must be plausible
            if prev.keyframe_id == ref_id and not g.motion.reachable(prev.pose.inverse() @ t_ref_j @ a.pose,
                                                                     prev.stamp_ns, obs.stamp_ns):
                continue
            if found is None or a.overlap > found[1].overlap:
                found = (j, a)
        g.stats.tracking_s += time.perf_counter() - start
        if found is None:
            return None
        j, a = found
        kf = g.keyframes[j]
        g.ref = j
        g.stats.reused += 1
        g.stats.reused_on_points += 1
        return g.placed_on_points(frame, kf, a.pose, g.verified_through(kf.keyframe_id))

    def graph_poses(self) -> dict:
        """{keyframe index: T_reference_keyframe} of the keyframes verified edges connect to the
        reference, composed along the fewest edges (breadth first)."""
        g = self.g
        ref = g.ref % len(g.keyframes)
        poses, queue = {ref: IDENTITY}, deque([ref])
        while queue:
            i = queue.popleft()
            for j in g.neighbours.get(i, ()):
                if j not in poses:
                    poses[j] = poses[i] @ g.edge_pose[i, j]
                    queue.append(j)
        return poses
