"""Keyframes, view-graph edges and a pose for every frame from a stream of detections
(paper 3.2-3.4, made live).

Each incoming frame is matched against the last keyframe ("tracking"): its verified
relative pose to that keyframe localizes it. It becomes a keyframe when tracking fails, or
when it shares too few objects with the keyframe, or has moved or turned too far from it.
A new keyframe is then matched against candidates: the few most recent keyframes plus the
keyframes whose bag-of-objects descriptor (mean of the object embeddings) is most similar,
so the cost per keyframe stays bounded however large the map grows. A frame of a stream
that would become a keyframe is first tried against older keyframes (a revisit): one that
verifies it becomes the reference instead, and the frame sends the edges a keyframe there
would have added, measured through itself, so that a map that stops growing still gets
the repeated measurements that outvote a wrong edge. Where its objects verify no older
keyframe, its depth points may: the view graph's own edges put older keyframes near it,
and one whose surfaces it aligns to becomes the reference all the same (no edge: nothing
verified the objects), so that the same place seen again adds no keyframe.

Whether the frames come from a continuous stream (a camera moving through the room) or are
separate views (photos seconds apart, an unordered collection) is decided from the frame
timing, per pair of frames, with no parameter: frames no more than ``max_frame_gap_s``
apart belong to one stream segment. Within a segment the motion prior holds (a camera
cannot turn or move arbitrarily fast: each tracked frame must be reachable from the
previous one, each edge from its source keyframe), and a relative pose resting on two
objects is kept towards a recent keyframe. Across segments nothing is known of the motion:
every edge, and tracking itself, needs ``min_retrieved_inliers`` verified objects (two
objects verify nothing beyond the minimal sample, and repeated furniture aliases), and a
keyframe that starts a segment retrieves ``unordered_retrieved_keyframes`` candidates.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from rfm_core.matching.classical import ClassicalMatcher, ObjectMatches
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.relative_pose import (
    RelativePose, YawPrior, estimate_relative_pose, track_on_points, with_surfaces)
from rfm_core.geometry import Pose4, wrap_angle, yaw_matrix
from rfm_core.observations import FrameObservations, FrameTrack, imu_relative_yaw
from rfm_core.settings import constant, setting

__all__ = ['KeyframeConfig', 'Keyframe', 'Edge', 'GraphStep', 'ViewGraphBuilder', 'bag_of_objects']


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
    max_frame_gap_s: float = setting(0.5, 'Frames further apart than this are separate views (photos): no motion '
                                     'prior between them; closer frames are one stream (s)', lo=0.01, hi=3600.0)
    max_yaw_rate_deg_s: float = setting(90.0, 'Motion prior within a stream: fastest turn of the camera (deg/s)',
                                        lo=1.0, hi=3600.0)
    max_speed_m_s: float = setting(1.5, 'Motion prior within a stream: fastest motion of the camera (m/s)',
                                   lo=0.01, hi=100.0)
    motion_slack_deg: float = constant(10.0, 'Motion prior: turn allowed on top of rate x time (deg)',
                                       lo=0.0, hi=180.0)
    motion_slack_m: float = constant(0.3, 'Motion prior: motion allowed on top of speed x time (m)', lo=0.0, hi=10.0)
    max_motion_edge_s: float = constant(1.0, "A keyframe that verified nothing is placed by the gyroscope's yaw and "
                                        'the predicted position at most this long after the last frame objects '
                                        'placed (s; 0: never)', lo=0.0, hi=60.0)
    velocity_window_s: float = constant(1.0, 'Motion prediction: the camera keeps the velocity of the frames '
                                        'objects placed over at most this long (s; 0: the position is held)',
                                        lo=0.0, hi=10.0)
    track_gate_m: float = constant(0.3, "Tracking: a box matches the reference's box predicted nearest within "
                                   'this (m) plus the distance the camera can have moved', lo=0.01, hi=5.0)
    imu_yaw_tolerance_deg: float = constant(3.0, "Within a stream, a relative pose's yaw may differ from the "
                                            "gyroscope's by this (deg) ...", lo=0.1, hi=180.0)
    imu_yaw_drift_deg_s: float = setting(1.0, "... plus this per second between the frames (the gyroscope's bias; "
                                         'raise it for an uncalibrated IMU, deg/s)', lo=0.0, hi=90.0)
    revisit_edges: int = constant(8, 'Measurements of one keyframe pair that revisiting frames may add (0: none)',
                                  lo=0, hi=16)
    min_retrieved_inliers: int = setting(3, 'Verified objects an edge needs where the motion prior cannot check '
                                         'it (separate views, retrieved keyframes)', lo=2, hi=100)


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


def _reversed(rel: RelativePose) -> RelativePose:
    """T_b_a of a verified T_a_b, its inliers as (b, a)."""
    return RelativePose(rel.pose.inverse(), rel.inliers[:, ::-1], rel.inlier_ious, rel.inlier_scores,
                        rel.mean_error, rel.num_matches)


def _without_objects(pose: Pose4) -> RelativePose:
    """A relative pose no object match supports (the motion's, or the depth points'): the least
    weight in the averaging."""
    return RelativePose(pose, np.zeros((0, 2), int), np.zeros(0), np.zeros(0), mean_error=1.0, num_matches=0)


def bag_of_objects(obs: FrameObservations) -> np.ndarray:
    """Retrieval descriptor of a frame: the unit mean of its object embeddings (zeros when
    it has none)."""
    if obs.embeddings.shape[1] == 0 or len(obs) == 0:
        return np.zeros(max(obs.embeddings.shape[1], 1))
    v = obs.embeddings.astype(np.float64).mean(0)
    return v / max(np.linalg.norm(v), 1e-9)


class GraphStep(NamedTuple):
    """What one frame did to the view graph: the keyframe it became (or None), the new
    keyframe's verified edges, and the frame's pose relative to a keyframe (None when it
    could not be localized)."""

    keyframe: Keyframe | None
    edges: list
    track: FrameTrack | None


@dataclass
class _Tracking:
    keyframe_id: int                  #: the keyframe the last frame was localized against
    pose: Pose4                       #: T_keyframe_frame of that frame
    stamp_ns: int
    observations: FrameObservations | None = None   #: that frame (None: it is the keyframe)
    relative: RelativePose | None = None            #: its verified pose to the keyframe
    verified_ns: int | None = None    #: stamp of the last frame placed by objects (None: this one)

    @property
    def last_verified_ns(self) -> int:
        return self.stamp_ns if self.verified_ns is None else self.verified_ns


@dataclass
class _Stats:
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
    motion_edges: int = 0             #: keyframes placed by the motion alone (tracking lost a moment)
    reused: int = 0                   #: frames that made an older keyframe the reference (revisits)
    reused_on_points: int = 0         #: ... of them aligned to it on their depth points (objects did not verify)
    handovers: int = 0                #: edges from the reference left to the keyframe revisited
    through: int = 0                  #: edges between keyframes measured through a revisiting frame
    last_candidates: list = field(default_factory=list)
    tracking_s: float = 0.0           #: time spent localizing frames against the last keyframe
    keyframe_s: float = 0.0           #: time spent matching new keyframes against candidates


class ViewGraphBuilder:
    """Feed frames with :meth:`add`; it returns the new keyframe (or None) and its edges."""

    def __init__(self, matching: MatchingConfig | None = None,
                 keyframes: KeyframeConfig | None = None, matcher=None):
        self.matching = matching or MatchingConfig()
        self.config = keyframes or KeyframeConfig()
        self.matcher = matcher or ClassicalMatcher(self.matching)
        self.keyframes: list = []
        self._desc_buffer = np.zeros((0, 0))      # grows by doubling: O(1) amortised append
        self.stats = _Stats()
        self._next_id = 0
        self._last_stamp = None           # of the previous frame (any frame: the stream's timing)
        self._segment = -1
        self._track_state: _Tracking | None = None
        self._placed: list = []           # (keyframe id, stamp, T_keyframe_frame.t) of frames objects placed
        self._carried = (None, np.zeros(3))   # (motion-placed keyframe id, the velocity carried into it)
        self._motion_placed: set = set()  # keyframes placed by a motion edge alone
        self._neighbours: dict = {}       # keyframe index -> indices it shares a verified edge with
        self._edge_pose: dict = {}        # (index i, index j) -> T_i_j of their verified edge
        self._index: dict = {}            # keyframe id -> index
        self._pair_edges: dict = {}       # (source id, target id) -> measurements of the pair sent
        self._ref = -1                    # index of the reference keyframe frames are tracked against

    @property
    def _tracking(self) -> _Tracking | None:
        """The last frame localized (or keyframe made), which predicts the next."""
        return self._track_state

    @_tracking.setter
    def _tracking(self, state: _Tracking | None) -> None:
        self._track_state = state
        if state is None:
            self._placed = []
        elif state.verified_ns is None:               # placed by objects: a sample of the motion
            window = self.config.velocity_window_s * 1e9
            self._placed = [p for p in self._placed
                            if p[0] == state.keyframe_id and 0 <= state.stamp_ns - p[1] <= window]
            self._placed.append((state.keyframe_id, state.stamp_ns, np.asarray(state.pose.t, float)))

    def _velocity(self) -> np.ndarray:
        """The camera's velocity (m/s) in the reference keyframe's frame over the frames
        objects placed on it within ``velocity_window_s`` (on a keyframe a motion edge
        placed: the velocity carried into it); zero when unknown."""
        prev = self._track_state
        if prev is not None and prev.verified_ns is not None:     # on a keyframe the motion placed
            return self._carried[1] if self._carried[0] == prev.keyframe_id else np.zeros(3)
        if prev is None or len(self._placed) < 2:
            return np.zeros(3)
        # (the setter keeps only samples on prev's keyframe, prev's the last)
        _, first_ns, first_t = self._placed[0]
        _, last_ns, last_t = self._placed[-1]
        dt = (last_ns - first_ns) / 1e9
        if dt < 0.2:
            return np.zeros(3)
        v = (last_t - first_t) / dt
        speed = float(np.linalg.norm(v))
        return v if speed <= self.config.max_speed_m_s else v * (self.config.max_speed_m_s / speed)

    @property
    def reference(self) -> Keyframe:
        """The keyframe frames are tracked against: the newest, or an older one revisited."""
        return self.keyframes[self._ref]

    def _relative(self, source: FrameObservations, target: FrameObservations,
                  matches=None, stream: bool = False, predicted: Pose4 | None = None) -> RelativePose | None:
        """T_source_target from matching target against source (or from ``matches`` of
        target against source, already computed). ``stream``: the two frames belong to one
        stream segment, so the gyroscope's rotation between them (when both carry it)
        constrains the yaw; ``predicted``: the motion's prediction of it (the depth points
        are aligned from it too: :func:`with_points`)."""
        if matches is None:
            matches = self.matcher.match(target, source)
        prior = None
        measured = self._imu_yaw(source, target) if stream else None     # (of T_source_target)
        if measured is not None:
            prior = YawPrior(measured[0], np.radians(measured[1]))
        rel = estimate_relative_pose(target.boxes, source.boxes, matches, self.matching, prior)
        if rel is None:
            return None
        rel.swap_index_order()                                       # as (source, target) index pairs
        return with_surfaces(rel, source, target, self.matching, predicted=predicted)

    def _reachable(self, motion: Pose4, stamp_a: int, stamp_b: int) -> bool:
        """The motion prior: a camera cannot turn or move arbitrarily fast. Catches the
        quarter-turn flips and look-alike matches that two objects cannot rule out."""
        cfg = self.config
        dt = abs(stamp_b - stamp_a) / 1e9
        if (np.degrees(abs(motion.yaw)) > cfg.max_yaw_rate_deg_s * dt + cfg.motion_slack_deg
                or np.linalg.norm(motion.t) > cfg.max_speed_m_s * dt + cfg.motion_slack_m):
            self.stats.implausible += 1
            return False
        return True

    def _imu_yaw(self, a: FrameObservations, b: FrameObservations):
        """(yaw of T_a_b as the gyroscope measured it, the deviation allowed in deg), or None
        when the frames share no integration epoch."""
        yaw = imu_relative_yaw(a, b)
        if yaw is None:
            return None
        cfg = self.config
        allowed = cfg.imu_yaw_tolerance_deg + cfg.imu_yaw_drift_deg_s * abs(b.stamp_ns - a.stamp_ns) / 1e9
        return yaw, allowed

    def _imu_agrees(self, t_a_b: Pose4, a: FrameObservations, b: FrameObservations) -> bool:
        """Whether a relative pose's yaw agrees with the rotation the gyroscope measured
        between the two frames (True when they share no integration epoch)."""
        measured = self._imu_yaw(a, b)
        if measured is None:
            return True
        yaw, allowed = measured
        if np.degrees(abs(wrap_angle(t_a_b.yaw - yaw))) > allowed:
            self.stats.imu_rejected += 1
            return False
        return True

    def _plausible(self, rel: RelativePose | None, a: FrameObservations, b: FrameObservations) -> RelativePose | None:
        """``rel`` (T_a_b) between two frames of one stream segment if the motion prior and
        the gyroscope allow it."""
        if rel is None or not self._reachable(rel.pose, a.stamp_ns, b.stamp_ns) or not self._imu_agrees(rel.pose, a, b):
            return None
        return rel

    def _predicted_pose(self, obs: FrameObservations) -> Pose4 | None:
        """T_keyframe_frame to the last keyframe as the previous tracked frame's position,
        moved on at the camera's recent velocity (:meth:`_velocity`), and the gyroscope's yaw
        predict it; None without a previous frame on that keyframe or without a gyroscope."""
        prev, last = self._tracking, self.reference
        if prev is None or prev.keyframe_id != last.keyframe_id:
            return None
        measured = self._imu_yaw(last.observations, obs)
        if measured is None:
            return None
        dt = (obs.stamp_ns - prev.stamp_ns) / 1e9
        return Pose4(measured[0], np.asarray(prev.pose.t) + self._velocity() * max(dt, 0.0))

    def _predicted_matches(self, keyframe: FrameObservations, obs: FrameObservations,
                           predicted: Pose4 | None) -> ObjectMatches | None:
        """Matches of the frame's boxes to the last keyframe's where the predicted pose
        (T_keyframe_frame, :meth:`_predicted_pose`) puts them (nearest centre, one-to-one,
        within the distance the camera can have moved plus the detector's noise): tracking
        without the object matcher. None when nothing predicts the pose."""
        if predicted is None or len(obs) == 0 or len(keyframe) == 0:
            return None
        moved = predicted.transform_points(obs.boxes[:, :3])          # frame boxes in the keyframe
        d = np.linalg.norm(moved[:, None, :] - keyframe.boxes[None, :, :3], axis=-1)
        dt = abs(obs.stamp_ns - self._tracking.stamp_ns) / 1e9
        gate = self.config.track_gate_m + self.config.max_speed_m_s * dt
        rows, cols = linear_sum_assignment(np.where(d < gate, d, 1e3))
        keep = d[rows, cols] < gate
        rows, cols = rows[keep], cols[keep]
        return ObjectMatches(rows, cols, 1.0 - d[rows, cols] / gate)

    def _track(self, obs: FrameObservations, stream: bool) -> RelativePose | None:
        """The frame's verified pose relative to the last keyframe (tracking), or None. In a
        stream the boxes are first matched where the previous frame's pose and the gyroscope
        predict them, and the object matcher is asked only when that does not verify; the
        motion from the previous tracked frame must be plausible. Across a gap the pose
        needs ``min_retrieved_inliers`` objects."""
        last = self.reference
        rel = None
        pose = self._predicted_pose(obs) if stream else None
        predicted = self._predicted_matches(last.observations, obs, pose)
        if predicted is not None and len(predicted) >= 2:
            rel = self._relative(last.observations, obs, predicted, stream=stream, predicted=pose)
            if rel is not None and len(rel.inliers) < max(2, 0.5 * len(predicted)):
                rel = None
            self.stats.predicted_tracking += rel is not None
        if rel is None:
            rel = self._relative(last.observations, obs, stream=stream, predicted=pose)
        if rel is None:
            return None
        if not stream:
            return rel if len(rel.inliers) >= self.config.min_retrieved_inliers else None
        prev = self._tracking
        if prev is not None and prev.keyframe_id == last.keyframe_id:
            # T_prev_frame = T_kf_prev^-1 T_kf_frame, over the time since the previous frame
            ok = self._reachable(prev.pose.inverse() @ rel.pose, prev.stamp_ns, obs.stamp_ns)
        else:
            ok = self._reachable(rel.pose, last.observations.stamp_ns, obs.stamp_ns)
        return rel if ok and self._imu_agrees(rel.pose, last.observations, obs) else None

    def _is_keyframe(self, obs: FrameObservations, last_rel: RelativePose | None,
                     reference: FrameObservations | None = None) -> bool:
        """Whether a frame becomes a keyframe, given its verified pose to the reference
        keyframe (or to ``reference``)."""
        if not self.keyframes or last_rel is None:
            return True
        cfg = self.config
        last = reference if reference is not None else self.reference.observations
        overlap = len(last_rel.inliers) / max(min(len(obs), len(last)), 1)
        return (overlap < cfg.min_overlap
                or np.linalg.norm(last_rel.pose.t) > cfg.max_translation_m
                or np.degrees(abs(last_rel.pose.yaw)) > cfg.max_yaw_deg)

    def candidates(self, descriptor: np.ndarray, separate: bool = False) -> list:
        """Indices of keyframes to match a new keyframe against (bounded in number);
        ``separate``: the keyframe starts a stream segment (more are retrieved)."""
        cfg = self.config
        n = len(self.keyframes)
        recent = list(range(max(0, n - cfg.recent_keyframes), n))
        older = n - len(recent)
        if n and self._ref % n not in recent:                 # the reference (a revisited keyframe)
            recent.append(self._ref % n)
        wanted = cfg.unordered_retrieved_keyframes if separate else cfg.retrieved_keyframes
        if older > 0 and wanted > 0 and self._desc_buffer.shape[1] == len(descriptor):
            sims = self._desc_buffer[:older] @ descriptor
            k = min(wanted, older)
            top = np.argpartition(-sims, k - 1)[:k]
            top = top[np.argsort(-sims[top])]
            recent += [int(i) for i in top if sims[i] >= cfg.min_retrieval_similarity and int(i) not in recent]
        return recent

    def _continues_stream(self, stamp_ns: int) -> bool:
        """Whether a frame continues the stream of the previous one (no more than
        ``max_frame_gap_s`` later); updates the stream segment."""
        last, self._last_stamp = self._last_stamp, stamp_ns
        stream = last is not None and 0 < stamp_ns - last <= self.config.max_frame_gap_s * 1e9
        if not stream:
            self._segment += 1
            self.stats.segments += 1
            self._tracking = None
        return stream

    @property
    def embedding_dim(self) -> int | None:
        """The length of the embeddings this graph holds (set by its first keyframe)."""
        return self._desc_buffer.shape[1] if self.keyframes else None

    def add(self, obs: FrameObservations) -> GraphStep:
        """Process one frame: returns the keyframe it became (or None), that keyframe's
        edges, and the frame's pose relative to a keyframe (or None). ValueError for
        detections whose embeddings differ in length from the graph's (one detector backend
        per graph: they cannot be matched or retrieved)."""
        dim = self.embedding_dim
        if dim is not None and len(obs) and max(obs.embeddings.shape[1], 1) != dim:
            raise ValueError(f'detections with {obs.embeddings.shape[1]}-value embeddings; this view graph holds '
                             f'{dim}-value ones (one detector backend per graph)')
        self.stats.frames += 1
        stream = self._continues_stream(obs.stamp_ns)
        if len(obs) < self.config.min_detections:
            step = self._point_tracked(obs, stream)
            self.stats.skipped += step is None
            return step if step is not None else GraphStep(None, [], None)
        # the pose to the last keyframe localizes the frame, decides whether it becomes a
        # keyframe, and is reused as that candidate's edge
        start = time.perf_counter()
        last_rel = self._track(obs, stream) if self.keyframes else None
        self.stats.tracking_s += time.perf_counter() - start
        if last_rel is not None and (self._weak(obs, stream) or not self._is_keyframe(obs, last_rel)):
            last = self.reference
            self._tracking = _Tracking(last.keyframe_id, last_rel.pose, obs.stamp_ns, obs, last_rel,
                                       verified_ns=self._verified_through(last.keyframe_id))
            self.stats.tracked += 1
            return GraphStep(None, [], FrameTrack(
                obs.stamp_ns, obs.frame_id, obs.gravity_cam, last.keyframe_id, last.observations.stamp_ns, last_rel.pose,
                len(last_rel.inliers), is_keyframe=False, continuous=stream))
        if stream and len(self.keyframes) > 1:
            revisit = self._revisit(obs, stream, last_rel)
            if revisit is None:
                revisit = self._revisit_on_points(obs, last_rel)
            if revisit is not None:
                return revisit
        prev = self._tracking
        if (stream and prev is not None and prev.observations is not None
                and len(prev.observations) >= self.config.min_detections
                and last_rel is None):
            bridged = self._bridge(obs)
            if bridged is not None:
                return bridged
        if self._weak(obs, stream):                                 # lost, but no keyframe (yet)
            step = self._point_tracked(obs, stream)
            return step if step is not None else GraphStep(None, [], None)
        return self._new_keyframe(obs, last_rel, stream)

    def _point_tracked(self, obs: FrameObservations, stream: bool) -> GraphStep | None:
        """A frame of a stream that objects did not localize, tracked on its depth points
        (:func:`track_on_points`): aligned to the reference keyframe's from the predicted pose
        (:meth:`_predicted_pose`), where the motion is plausible; None otherwise. A direction
        the points leave free (at most one) keeps the prediction, and only within
        ``max_motion_edge_s`` of the last frame placed in full. The frame becomes no keyframe;
        a bridge from it to a later frame weighs its pose as a motion edge (no object matches)."""
        cfg, prev = self.config, self._tracking
        if not (stream and self.keyframes and prev is not None):
            return None
        ref = self.reference
        predicted = self._predicted_pose(obs)                         # T_ref_frame
        if predicted is None:
            return None
        start = time.perf_counter()
        found = track_on_points(predicted, ref.observations, obs, self.matching)
        self.stats.tracking_s += time.perf_counter() - start
        if found is None:
            return None
        full = found.free == 0
        if found.free > 1 or not full and obs.stamp_ns - prev.last_verified_ns > cfg.max_motion_edge_s * 1e9:
            return None
        if not (self._reachable(prev.pose.inverse() @ found.pose, prev.stamp_ns, obs.stamp_ns)
                and self._imu_agrees(found.pose, ref.observations, obs)):
            return None
        self.stats.point_tracked += 1
        verified_ns = self._verified_through(ref.keyframe_id) if full else prev.last_verified_ns
        return self._placed_on_points(obs, ref, found.pose, verified_ns)

    def _placed_on_points(self, obs: FrameObservations, keyframe: Keyframe, pose: Pose4,
                          verified_ns: int | None) -> GraphStep:
        """The frame tracked against ``keyframe`` at ``pose`` (T_keyframe_frame), which its
        depth points gave: no object verified it."""
        self._tracking = _Tracking(keyframe.keyframe_id, pose, obs.stamp_ns, obs, _without_objects(pose),
                                   verified_ns=verified_ns)
        self.stats.tracked += 1
        return GraphStep(None, [], FrameTrack(
            obs.stamp_ns, obs.frame_id, obs.gravity_cam, keyframe.keyframe_id, keyframe.observations.stamp_ns, pose, 0,
            is_keyframe=False, continuous=True))

    def _weak(self, obs: FrameObservations, stream: bool, pose: Pose4 | None = None) -> bool:
        """Whether a frame of a stream has too few detections to become a new keyframe
        where the map already has one: a neighbour of the reference (not the reference
        itself, which it failed to track against) within ``max_translation_m`` and
        ``max_yaw_deg`` of its pose relative to the reference (``pose``, else predicted)."""
        cfg = self.config
        if not (stream and self.keyframes and len(obs) < cfg.min_keyframe_detections):
            return False
        pose = pose if pose is not None else self._predicted_pose(obs)        # T_ref_frame
        if pose is None:
            return False
        ref = self._ref % len(self.keyframes)
        for j in self._neighbours.get(ref, ()):
            if (self._edge_pose[ref, j].inverse() @ pose).within(cfg.max_translation_m, cfg.max_yaw_deg):  # T_j_frame
                return True
        return False

    def _revisit(self, obs: FrameObservations, stream: bool, last_rel: RelativePose | None = None) -> GraphStep | None:
        """A frame about to become a keyframe, localized against older keyframes instead
        (the reference's neighbours two edges away, then the retrieved ones): of those that
        verify it with ``min_retrieved_inliers`` objects and overlap it as the reference would
        need, the one with the most inliers becomes the reference and the frame is tracked
        against it."""
        start = time.perf_counter()
        ref = self._ref % len(self.keyframes)
        # the reference's neighbourhood in the graph (two edges away: after one revisit, the
        # keyframes of the earlier pass around it), then the retrieved ones
        near = set(self._neighbours.get(ref, ()))
        near |= {j for i in near for j in self._neighbours.get(i, ())}
        cand = sorted(near - {ref}, reverse=True)[:self.config.retrieved_keyframes + self.config.recent_keyframes]
        cand += [i for i in self.candidates(bag_of_objects(obs), separate=not stream) if i != ref and i not in cand]
        found, verified = None, []
        if cand:
            matches = self.matcher.match_many(obs, [self.keyframes[i].observations for i in cand])
            for i, m in zip(cand, matches):
                source = self.keyframes[i].observations
                rel = self._relative(source, obs, m, stream=False)
                if rel is None or len(rel.inliers) < self.config.min_retrieved_inliers:
                    continue
                verified.append((i, rel))
                if (not self._is_keyframe(obs, rel, source)
                        and (found is None or len(rel.inliers) > len(found[1].inliers))):
                    found = (i, rel)
        self.stats.tracking_s += time.perf_counter() - start
        return None if found is None else self._revisited(obs, stream, *found, last_rel, verified)

    def _graph_poses(self) -> dict:
        """{keyframe index: T_reference_keyframe} of the keyframes verified edges connect to the
        reference, composed along the fewest edges (breadth first)."""
        ref = self._ref % len(self.keyframes)
        poses, queue = {ref: Pose4(0.0, (0.0, 0.0, 0.0))}, deque([ref])
        while queue:
            i = queue.popleft()
            for j in self._neighbours.get(i, ()):
                if j not in poses:
                    poses[j] = poses[i] @ self._edge_pose[i, j]
                    queue.append(j)
        return poses

    def _revisit_on_points(self, obs: FrameObservations, last_rel: RelativePose | None) -> GraphStep | None:
        """A frame of a stream about to become a keyframe, aligned on its depth points to an
        older keyframe the view graph places near it:
        of the three nearest within ``max_translation_m`` and ``max_yaw_deg`` of its pose to the
        reference (``last_rel``, else predicted), the one whose surfaces it aligns to in every
        direction with the most of its points becomes the reference, and the frame is tracked
        against it (no edge: no object verified it); None where none aligns."""
        cfg, prev = self.config, self._tracking
        pose = last_rel.pose if last_rel is not None else self._predicted_pose(obs)           # T_ref_frame
        if pose is None or prev is None:
            return None
        start = time.perf_counter()
        n = len(self.keyframes)
        skip = set(range(max(0, n - cfg.recent_keyframes), n)) | {self._ref % n}      # the recent ones, the reference
        near = []
        for j, t_ref_j in self._graph_poses().items():
            t_j_frame = t_ref_j.inverse() @ pose
            if j not in skip and t_j_frame.within(cfg.max_translation_m, cfg.max_yaw_deg):
                near.append((float(np.linalg.norm(t_j_frame.t)), j, t_ref_j, t_j_frame))
        ref_id = self.reference.keyframe_id
        found = None
        for _, j, t_ref_j, t_j_frame in sorted(near, key=lambda n: n[0])[:3]:
            kf = self.keyframes[j].observations
            a = track_on_points(t_j_frame, kf, obs, self.matching)
            if a is None or a.free or not self._imu_agrees(a.pose, kf, obs):
                continue
            # the motion from the previous frame (on the reference) through the graph must be plausible
            if prev.keyframe_id == ref_id and not self._reachable(prev.pose.inverse() @ t_ref_j @ a.pose,
                                                                  prev.stamp_ns, obs.stamp_ns):
                continue
            if found is None or a.overlap > found[1].overlap:
                found = (j, a)
        self.stats.tracking_s += time.perf_counter() - start
        if found is None:
            return None
        j, a = found
        kf = self.keyframes[j]
        self._ref = j
        self.stats.reused += 1
        self.stats.reused_on_points += 1
        return self._placed_on_points(obs, kf, a.pose, self._verified_through(kf.keyframe_id))

    def _revisited(self, obs: FrameObservations, stream: bool, i: int, rel: RelativePose,
                   last_rel: RelativePose | None, verified: list) -> GraphStep:
        """The frame tracked against keyframe index ``i`` (``rel``), which becomes the
        reference, with the edges it measured (:attr:`KeyframeConfig.revisit_edges`):
        ``last_rel`` its pose to the reference it leaves, ``verified`` the other keyframes
        (index, pose) it verified against."""
        edges = [self._handover(obs, i, rel, last_rel)]
        # the frame, as a keyframe would, links the keyframes it verified against: each to the new reference
        edges += [self._through(self.keyframes[i].keyframe_id, self.keyframes[j].keyframe_id,
                                rel.pose @ rel_j.pose.inverse(), [rel, _reversed(rel_j)])
                  for j, rel_j in verified if j != i]
        edges = [e for e in edges if e is not None and self._count_pair(e) <= self.config.revisit_edges]
        self._ref = i
        kf = self.keyframes[i]
        self._tracking = _Tracking(kf.keyframe_id, rel.pose, obs.stamp_ns, obs, rel,
                                   verified_ns=self._verified_through(kf.keyframe_id))
        self.stats.tracked += 1
        self.stats.reused += 1
        return GraphStep(None, edges, FrameTrack(
            obs.stamp_ns, obs.frame_id, obs.gravity_cam, kf.keyframe_id, kf.observations.stamp_ns, rel.pose,
            len(rel.inliers), is_keyframe=False, continuous=stream))

    def _handover(self, obs: FrameObservations, i: int, rel: RelativePose,
                  last_rel: RelativePose | None) -> Edge | None:
        """The edge from the reference the frame leaves to keyframe index ``i`` it revisits
        (T_reference_i through the frame: its pose to the reference, ``last_rel`` or through
        the previous tracked frame, and ``rel``, its pose to ``i``), or None. A revisit adds
        no keyframe, but its edge is the measurement a new keyframe would have added."""
        ref = self.reference
        legs = []
        if last_rel is not None:
            t_ref_frame = last_rel.pose
            legs.append(last_rel)
        else:
            prev = self._tracking
            if (prev is None or prev.observations is None or prev.relative is None
                    or prev.keyframe_id != ref.keyframe_id):
                return None
            step = self._plausible(self._relative(prev.observations, obs, stream=True), prev.observations, obs)
            if step is None:
                return None
            t_ref_frame = prev.pose @ step.pose
            legs += [prev.relative, step]
        legs.append(_reversed(rel))                                                  # (frame, i)
        edge = self._through(ref.keyframe_id, self.keyframes[i].keyframe_id, t_ref_frame @ rel.pose.inverse(), legs)
        self.stats.handovers += edge is not None
        return edge

    def _through(self, source_id: int, target_id: int, pose: Pose4, legs: list) -> Edge | None:
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
        self.stats.through += 1
        return Edge(source_id, target_id, RelativePose(
            pose, inliers, np.ones(len(inliers)), scores, max(leg.mean_error for leg in legs),
            max(len(inliers), int(np.ceil(len(inliers) / max(ratio, 1e-3))))))

    def _count_pair(self, edge: Edge) -> int:
        """Count a measurement of the edge's keyframe pair; returns the pair's count."""
        key = (edge.source_id, edge.target_id)
        self._pair_edges[key] = self._pair_edges.get(key, 0) + 1
        return self._pair_edges[key]

    def _bridge(self, obs: FrameObservations) -> GraphStep | None:
        """Tracking failed against the last keyframe: if the frame verifies against the last
        frame that was tracked (moments earlier), that frame becomes the keyframe (it is linked
        to the last keyframe by its tracked pose) and this frame is tracked against it."""
        prev = self._tracking
        if prev.keyframe_id == self.reference.keyframe_id and self._weak(prev.observations, True, prev.pose):
            return None
        start = time.perf_counter()
        rel = self._plausible(self._relative(prev.observations, obs, stream=True), prev.observations, obs)
        self.stats.tracking_s += time.perf_counter() - start
        if rel is None:
            return None
        # the previous frame becomes a keyframe, linked by its tracked pose
        step = self._new_keyframe(prev.observations, prev.relative, True)
        keyframe = step.keyframe
        self._tracking = _Tracking(keyframe.keyframe_id, rel.pose, obs.stamp_ns, obs, rel,
                                   verified_ns=self._verified_through(keyframe.keyframe_id))
        self.stats.bridged += 1
        return GraphStep(keyframe, step.edges, FrameTrack(
            obs.stamp_ns, obs.frame_id, obs.gravity_cam, keyframe.keyframe_id, keyframe.observations.stamp_ns,
            rel.pose, len(rel.inliers), is_keyframe=False, continuous=True))

    def _verified_through(self, keyframe_id: int) -> int | None:
        """``verified_ns`` of a frame localized against ``keyframe_id``: objects place it
        relative to that keyframe, but a keyframe placed by a motion edge alone is no better
        placed than the last frame objects placed before it (None: the frame itself)."""
        if keyframe_id in self._motion_placed and self._tracking is not None:
            return self._tracking.last_verified_ns
        return None

    def _motion_edge(self, obs: FrameObservations) -> RelativePose | None:
        """Where the camera went while tracking was lost for a moment: the last keyframe to
        this frame as the gyroscope's yaw and the last tracked frame's position, moved on at
        the camera's recent velocity, predict it, refined on the two frames' surfaces. Where
        the depth points fix every direction (``rel.on_points``) it is a measurement;
        otherwise at most ``max_motion_edge_s`` after the last frame that objects (or points)
        placed: motion edges never chain longer. It has no object matches and the least
        weight in the averaging: it only places a stretch that nothing else links."""
        predicted = self._predicted_pose(obs)
        if predicted is None:
            return None
        rel = _without_objects(predicted)
        rel = with_surfaces(rel, self.reference.observations, obs, self.matching)
        # measured from the last frame objects placed: motion edges never chain past it
        if not rel.on_points and obs.stamp_ns - self._tracking.last_verified_ns > self.config.max_motion_edge_s * 1e9:
            return None
        self.stats.motion_edges += 1
        return rel

    def _new_keyframe(self, obs: FrameObservations, last_rel: RelativePose | None, stream: bool) -> GraphStep:
        start = time.perf_counter()
        descriptor = bag_of_objects(obs)
        keyframe = Keyframe(self._next_id, obs, descriptor, self._segment)
        self._next_id += 1
        edges = []
        cand = self.candidates(descriptor, separate=not stream)
        self.stats.last_candidates = [self.keyframes[i].keyframe_id for i in cand]
        last = self._ref % len(self.keyframes) if self.keyframes else -1      # the reference: last_rel's
        # two verified objects suffice for a recent neighbour of the same stream segment,
        # where the motion prior has checked the pose
        recent_from = len(self.keyframes) - self.config.recent_keyframes
        others = [i for i in cand if i != last]            # matched in one batch
        batched = dict(zip(others, self.matcher.match_many(obs, [self.keyframes[i].observations for i in others])))
        for i in cand:
            source = self.keyframes[i]
            same = source.segment == keyframe.segment
            self.stats.pairs_tested += 1
            if i == last:
                rel = last_rel
            else:
                rel = self._relative(source.observations, obs, batched[i], stream=same)
                if same:
                    rel = self._plausible(rel, source.observations, obs)
            if rel is not None and ((same and (i >= recent_from or i == last))
                                    or len(rel.inliers) >= self.config.min_retrieved_inliers):
                edges.append(Edge(source.keyframe_id, keyframe.keyframe_id, rel))
        if not edges and stream and self.keyframes:
            motion = self._motion_edge(obs)
            if motion is not None:
                edges.append(Edge(self.reference.keyframe_id, keyframe.keyframe_id, motion))
                if not motion.on_points:                           # placed by the motion alone
                    self._motion_placed.add(keyframe.keyframe_id)
                # the camera keeps its velocity through the new keyframe (a vector: rotated only)
                self._carried = (keyframe.keyframe_id, yaw_matrix(motion.pose.yaw).T @ self._velocity())
        n = len(self.keyframes)
        if n == 0:                                                 # first keyframe: sets the length
            self._desc_buffer = np.zeros((64, len(descriptor)))
        elif n == len(self._desc_buffer):
            self._desc_buffer = np.vstack([self._desc_buffer, np.zeros_like(self._desc_buffer)])
        self._desc_buffer[n] = descriptor
        self.keyframes.append(keyframe)
        self._ref = len(self.keyframes) - 1
        self._index[keyframe.keyframe_id] = self._ref
        for e in edges:
            if e.relative.num_matches:                             # verified by objects (not motion)
                i = self._index[e.source_id]
                self._neighbours.setdefault(i, set()).add(self._ref)
                self._neighbours.setdefault(self._ref, set()).add(i)
                self._edge_pose[i, self._ref] = e.relative.pose
                self._edge_pose[self._ref, i] = e.relative.pose.inverse()
        for e in edges:
            self._count_pair(e)
        self.stats.keyframes += 1
        self.stats.tracked += 1
        self.stats.edges += len(edges)
        self.stats.keyframe_s += time.perf_counter() - start
        self._tracking = _Tracking(keyframe.keyframe_id, Pose4(0.0, (0.0, 0.0, 0.0)), obs.stamp_ns, None,
                                   verified_ns=self._verified_through(keyframe.keyframe_id))
        return GraphStep(keyframe, edges, FrameTrack(
            obs.stamp_ns, obs.frame_id, obs.gravity_cam, keyframe.keyframe_id, obs.stamp_ns,
            Pose4(0.0, (0.0, 0.0, 0.0)), 0, is_keyframe=True, continuous=stream))
