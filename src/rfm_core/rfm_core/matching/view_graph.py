"""Keyframes, view-graph edges and a pose for every frame from a stream of detections
(paper 3.2-3.4, made live).

Each frame goes through the localizers in order until one places it (:meth:`ViewGraphBuilder.add`):

1. :class:`~rfm_core.matching.tracking.Tracking`: against the reference keyframe, by its
   objects; the frame stays a frame when it shares enough of them and is near;
2. :class:`~rfm_core.matching.revisits.Revisit`: against older keyframes, by its objects
   (a place seen again: the older keyframe becomes the reference);
3. :class:`~rfm_core.matching.revisits.RevisitOnPoints`: the same by its depth points;
4. :class:`~rfm_core.matching.keyframes.Bridge`: tracking failed, and the previous frame,
   tracked moments earlier, becomes the keyframe;
5. :class:`~rfm_core.matching.tracking.PointTracking`: on its depth points alone, where it
   has too few detections to be a keyframe the map needs (or to be matched at all);
6. :class:`~rfm_core.matching.keyframes.NewKeyframe`: it becomes a keyframe, matched against
   candidates (recent and retrieved keyframes).

The stream's motion (:mod:`rfm_core.matching.motion`) decides what is one stream and checks
every relative pose within it. Each localizer is a small class with its options section of
:class:`ViewGraphConfig`; this module holds the graph's state they share.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.geometry import Pose4
from rfm_core.matching.classical import ClassicalMatcher
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.graph import (Edge, Frame, GraphStats, GraphStep, Keyframe, TrackState, bag_of_objects, tracked,
                                     without_objects)
from rfm_core.matching.keyframes import Bridge, KeyframeConfig, NewKeyframe, weak
from rfm_core.matching.motion import MotionConfig, StreamMotion
from rfm_core.matching.relative_pose import (RelativePose, YawPrior, estimate_by_consensus, estimate_on_full_boxes,
                                             estimate_relative_pose, with_surfaces)
from rfm_core.matching.revisits import Revisit, RevisitConfig, RevisitOnPoints
from rfm_core.matching.tracking import PointTracking, Tracking, TrackingConfig
from rfm_core.observations import FrameObservations
from rfm_core.settings import section

__all__ = ['ViewGraphConfig', 'KeyframeConfig', 'MotionConfig', 'Keyframe', 'Edge', 'GraphStep', 'ViewGraphBuilder',
           'bag_of_objects']


@dataclass(frozen=True)
class ViewGraphConfig:
    keyframes: KeyframeConfig = section(KeyframeConfig, 'keyframes and the keyframes a new one is matched against')
    motion: MotionConfig = section(MotionConfig, "a stream's motion prior and the gyroscope's check")
    tracking: TrackingConfig = section(TrackingConfig, 'tracking against the reference keyframe')
    revisits: RevisitConfig = section(RevisitConfig, 'revisits of older keyframes')


class ViewGraphBuilder:
    """Feed frames with :meth:`add`; it returns the new keyframe (or None), the edges the
    frame added and its track."""

    def __init__(self, matching: MatchingConfig | None = None, config: ViewGraphConfig | None = None,
                 matcher=None):
        self.matching = matching or MatchingConfig()
        self.config = config or ViewGraphConfig()
        self.matcher = matcher or ClassicalMatcher(self.matching)
        self.stats = GraphStats()
        self.motion = StreamMotion(self.config.motion, self.stats)
        self.keyframes: list = []
        self.descriptors = np.zeros((0, 0))      # keyframes' bag-of-objects, by index (grows by doubling)
        self._dim: int | None = None             # their length
        self.next_id = 0
        self.ref = -1                            # index of the reference keyframe frames are tracked against
        self.separate = False                    # the frame being added is a separate view (no stream before it)
        self.neighbours: dict = {}               # keyframe index -> indices it shares a verified edge with
        self.edge_pose: dict = {}                # (index i, index j) -> T_i_j of their verified edge
        self.motion_placed: set = set()          # keyframes placed by a motion edge alone
        self._state: TrackState | None = None
        self._index: dict = {}                   # keyframe id -> index
        self._pair_edges: dict = {}              # (source id, target id) -> measurements of the pair sent
        # the localizers, in the order a frame is tried (see the module)
        self.tracking = Tracking(self)
        self.revisit = Revisit(self)
        self.revisit_on_points = RevisitOnPoints(self)
        self.bridge = Bridge(self)
        self.point_tracking = PointTracking(self)
        self.new_keyframe = NewKeyframe(self)

    def add(self, obs: FrameObservations) -> GraphStep:
        """Process one frame: the keyframe it became (or None), the edges it added, and its
        pose relative to a keyframe (or None). ValueError for detections whose embeddings
        differ in length from the graph's (one detector backend per graph: they cannot be
        matched or retrieved)."""
        dim = self.embedding_dim
        if dim is not None and len(obs) and max(obs.embeddings.shape[1], 1) != dim:
            raise ValueError(f'detections with {obs.embeddings.shape[1]}-value embeddings; this view graph holds '
                             f'{dim}-value ones (one detector backend per graph)')
        self.stats.frames += 1
        frame = Frame(obs, self.motion.continues(obs))
        self.separate = not frame.stream
        if not frame.stream:
            self.state = None                    # nothing predicts a separate view
        if len(obs) < self.config.keyframes.min_detections:           # too few objects to match
            if not self.keyframes and obs.odometry is not None:
                return self.new_keyframe(frame)   # a robot's map starts at once: odometry links on
            step = self.point_tracking(frame)
            self.stats.skipped += step is None
            return step if step is not None else GraphStep(None, [], None)
        for localize in (self.tracking, self.revisit, self.revisit_on_points, self.bridge):
            step = localize(frame)
            if step is not None:
                return step
        if weak(self, obs, frame.stream):                             # lost, but no keyframe (the map has one)
            step = self.point_tracking(frame)
            return step if step is not None else GraphStep(None, [], None)
        return self.new_keyframe(frame)

    # ------------------------------------------------------------------ shared state

    @property
    def state(self) -> TrackState | None:
        """The last frame localized (or keyframe made), which predicts the next."""
        return self._state

    @state.setter
    def state(self, state: TrackState | None) -> None:
        self._state = state
        self.motion.observe(state)

    @property
    def reference(self) -> Keyframe:
        """The keyframe frames are tracked against: the newest, or an older one revisited."""
        return self.keyframes[self.ref]

    @property
    def embedding_dim(self) -> int | None:
        """The length of the embeddings this graph holds (set by its first keyframe with objects)."""
        return self._dim

    def predicted_pose(self, obs: FrameObservations) -> Pose4 | None:
        """T_reference_frame as the stream's motion predicts it (None: nothing predicts it)."""
        return self.motion.predicted_pose(self.state, self.reference, obs)

    def relative(self, source: FrameObservations, target: FrameObservations,
                 matches=None, stream: bool = False, predicted: Pose4 | None = None) -> RelativePose | None:
        """T_source_target from matching target against source (or from ``matches`` of
        target against source, already computed), corrected by the floor, the walls and the
        depth points. ``stream``: the two frames belong to one stream segment, so the
        gyroscope's rotation between them (when both carry it) constrains the yaw;
        ``predicted``: the motion's prediction of it (the depth points are aligned from it too).
        A separate view (:attr:`separate`) that the fitted boxes do not relate to a keyframe of
        another segment by ``min_retrieved_inliers`` objects is related by the full boxes where
        its visible surfaces agree (:func:`estimate_on_full_boxes`), matched by the matcher, else
        by the layout of the boxes alone (:func:`estimate_by_consensus`)."""
        if matches is None:
            matches = self.matcher.match(target, source)
        prior = None
        measured = self.motion.imu_yaw(source, target) if stream else None     # (of T_source_target)
        if measured is not None:
            prior = YawPrior(measured[0], np.radians(measured[1]))
        rel = estimate_relative_pose(target.boxes, source.boxes, matches, self.matching, prior)
        if rel is not None:
            rel.swap_index_order()                                   # as (source, target) index pairs
        few = rel is None or len(rel.inliers) < self.config.keyframes.min_retrieved_inliers
        if self.separate and not stream and few:
            full = estimate_on_full_boxes(target, source, self.matcher, self.matching)
            if full is None or len(full.inliers) < self.config.keyframes.min_retrieved_inliers:
                full = estimate_by_consensus(target, source, self.matching) or full
            rel = rel if full is None else full.swap_index_order()
        if rel is None:
            return None
        return with_surfaces(rel, source, target, self.matching, predicted=predicted)

    def verified_through(self, keyframe_id: int) -> int | None:
        """``verified_ns`` of a frame localized against ``keyframe_id``: objects place it
        relative to that keyframe, but a keyframe placed by a motion edge alone is no better
        placed than the last frame objects placed before it (None: the frame itself)."""
        if keyframe_id in self.motion_placed and self.state is not None:
            return self.state.last_verified_ns
        return None

    def placed_on_points(self, frame: Frame, keyframe: Keyframe, pose: Pose4, verified_ns: int | None) -> GraphStep:
        """The frame tracked against ``keyframe`` at ``pose`` (T_keyframe_frame), which its
        depth points gave: no object verified it."""
        obs = frame.obs
        self.state = TrackState(keyframe.keyframe_id, pose, obs.stamp_ns, obs, without_objects(pose),
                                verified_ns=verified_ns)
        self.stats.tracked += 1
        return GraphStep(None, [], tracked(frame, keyframe, pose, 0, continuous=True))

    def count_pair(self, edge: Edge) -> int:
        """Count a measurement of the edge's keyframe pair; returns the pair's count."""
        key = (edge.source_id, edge.target_id)
        self._pair_edges[key] = self._pair_edges.get(key, 0) + 1
        return self._pair_edges[key]

    def add_keyframe(self, keyframe: Keyframe, edges: list) -> None:
        """A new keyframe with its edges: indexed for retrieval, linked to its neighbours,
        and the reference from now on."""
        n = len(self.keyframes)
        if self._dim is None and len(keyframe.observations):      # the first with objects sets the length
            self._dim = len(keyframe.descriptor)
        width = self._dim or 1
        if self.descriptors.shape[1] != width:                     # (a robot's object-less keyframes: zeros)
            self.descriptors = np.zeros((max(64, 2 * n), width))
        elif n == len(self.descriptors):
            self.descriptors = np.vstack([self.descriptors, np.zeros_like(self.descriptors)])
        if len(keyframe.descriptor) == width:
            self.descriptors[n] = keyframe.descriptor
        self.keyframes.append(keyframe)
        self.ref = len(self.keyframes) - 1
        self._index[keyframe.keyframe_id] = self.ref
        for e in edges:
            if e.relative.num_matches:                             # verified by objects (not motion)
                i = self._index[e.source_id]
                self.neighbours.setdefault(i, set()).add(self.ref)
                self.neighbours.setdefault(self.ref, set()).add(i)
                self.edge_pose[i, self.ref] = e.relative.pose
                self.edge_pose[self.ref, i] = e.relative.pose.inverse()
        for e in edges:
            self.count_pair(e)
