"""Keyframes and view-graph edges from a stream of detections (paper 3.2-3.4, made live).

Each incoming frame is matched against the last keyframe. It becomes a keyframe when it
shares too few objects with it, or has moved or turned too far from it. A new keyframe is
then matched against candidates: the few most recent keyframes plus the keyframes whose
bag-of-objects descriptor (mean of the object embeddings) is most similar, so the cost per
keyframe stays bounded however large the map grows. Every verified relative pose becomes
an edge, except that a pose resting on only two objects is kept only towards a recent
keyframe of an ordered capture, where the motion prior has checked it (two objects verify
nothing beyond the minimal sample, and repeated furniture aliases). An unordered
collection (``motion_prior`` off) gets more retrieved candidates instead, since there
"recent" means nothing.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rfm_core.matching.classical import ClassicalMatcher
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.relative_pose import RelativePose, estimate_relative_pose
from rfm_core.observations import FrameObservations

__all__ = ['KeyframeConfig', 'Keyframe', 'Edge', 'ViewGraphBuilder', 'bag_of_objects']


@dataclass(frozen=True)
class KeyframeConfig:
    min_overlap: float = 0.6          #: new keyframe when fewer than this share of objects match
    max_translation_m: float = 0.5    #: ... or when it moved farther than this
    max_yaw_deg: float = 20.0         #: ... or turned more than this
    min_detections: int = 2           #: frames with fewer detections are skipped
    min_interval_s: float = 0.0       #: no new keyframe sooner than this after the last one
    recent_keyframes: int = 3         #: always match against this many latest keyframes
    retrieved_keyframes: int = 5      #: plus this many most similar older ones
    unordered_retrieved_keyframes: int = 15   #: ... without the motion prior (an unordered
                                      #: collection: retrieval is what finds the overlaps)
    min_retrieval_similarity: float = 0.3
    max_yaw_rate_deg_s: float = 90.0  #: motion prior: an edge turning faster than this ...
    max_speed_m_s: float = 1.5        #: ... or moving faster (plus the slack below) is rejected
    motion_slack_deg: float = 10.0    #: allowance on top of rate x time (detector noise)
    motion_slack_m: float = 0.3
    motion_prior: bool = True         #: off for unordered collections (stamps mean nothing);
                                      #: then every edge needs min_retrieved_inliers
    min_retrieved_inliers: int = 3    #: edges to retrieved (not recent) keyframes need this many
                                      #: verified objects: two objects verify nothing beyond
                                      #: the minimal sample, and repeated furniture aliases


@dataclass
class Keyframe:
    keyframe_id: int
    observations: FrameObservations
    descriptor: np.ndarray            #: unit bag-of-objects descriptor (D,)


@dataclass
class Edge:
    """A verified relative pose: ``relative.pose`` is T_source_target (maps the target
    keyframe's gravity-aligned frame into the source's), ``relative.inliers`` are
    (source detection, target detection) index pairs."""

    source_id: int
    target_id: int
    relative: RelativePose


def bag_of_objects(obs: FrameObservations) -> np.ndarray:
    """Retrieval descriptor of a frame: the unit mean of its object embeddings (zeros when
    it has none)."""
    if obs.embeddings.shape[1] == 0 or len(obs) == 0:
        return np.zeros(max(obs.embeddings.shape[1], 1))
    v = obs.embeddings.astype(np.float64).mean(0)
    return v / max(np.linalg.norm(v), 1e-9)


@dataclass
class _Stats:
    frames: int = 0
    skipped: int = 0
    keyframes: int = 0
    pairs_tested: int = 0
    edges: int = 0
    implausible: int = 0
    last_candidates: list = field(default_factory=list)


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

    def _relative(self, source: FrameObservations, target: FrameObservations,
                  matches=None) -> RelativePose | None:
        """T_source_target from matching target against source (or from ``matches`` of
        target against source, already computed)."""
        if matches is None:
            matches = self.matcher.match(target, source)
        rel = estimate_relative_pose(target.boxes, source.boxes, matches, self.matching)
        if rel is None:
            return None
        rel.inliers = rel.inliers[:, ::-1].copy()        # as (source, target) index pairs
        rel.corner_inliers = [(ib, cb, ia, ca, e) for ia, ca, ib, cb, e in rel.corner_inliers]
        return rel

    def _plausible(self, rel: RelativePose | None, stamp_a: int, stamp_b: int) -> RelativePose | None:
        """The motion prior: a camera cannot turn or move arbitrarily fast. Catches the
        quarter-turn flips and look-alike matches that two objects cannot rule out."""
        cfg = self.config
        if rel is None or not cfg.motion_prior:
            return rel
        dt = abs(stamp_b - stamp_a) / 1e9
        if (np.degrees(abs(rel.pose.yaw)) > cfg.max_yaw_rate_deg_s * dt + cfg.motion_slack_deg
                or np.linalg.norm(rel.pose.t) > cfg.max_speed_m_s * dt + cfg.motion_slack_m):
            self.stats.implausible += 1
            return None
        return rel

    def _too_soon(self, obs: FrameObservations) -> bool:
        """Whether ``min_interval_s`` has not yet passed since the last keyframe."""
        if self.config.min_interval_s <= 0 or not self.keyframes:
            return False
        dt = obs.stamp_ns - self.keyframes[-1].observations.stamp_ns
        return 0 <= dt < self.config.min_interval_s * 1e9

    def _is_keyframe(self, obs: FrameObservations, last_rel: RelativePose | None) -> bool:
        """Whether a frame becomes a keyframe, given its verified pose to the last keyframe."""
        if not self.keyframes or last_rel is None:
            return True
        cfg = self.config
        last = self.keyframes[-1].observations
        overlap = len(last_rel.inliers) / max(min(len(obs), len(last)), 1)
        return (overlap < cfg.min_overlap
                or np.linalg.norm(last_rel.pose.t) > cfg.max_translation_m
                or np.degrees(abs(last_rel.pose.yaw)) > cfg.max_yaw_deg)

    def candidates(self, descriptor: np.ndarray) -> list:
        """Indices of keyframes to match a new keyframe against (bounded in number)."""
        cfg = self.config
        n = len(self.keyframes)
        recent = list(range(max(0, n - cfg.recent_keyframes), n))
        older = n - len(recent)
        wanted = cfg.retrieved_keyframes if cfg.motion_prior else cfg.unordered_retrieved_keyframes
        if older > 0 and wanted > 0 and self._desc_buffer.shape[1] == len(descriptor):
            sims = self._desc_buffer[:older] @ descriptor
            k = min(wanted, older)
            top = np.argpartition(-sims, k - 1)[:k]
            top = top[np.argsort(-sims[top])]
            recent += [int(i) for i in top if sims[i] >= cfg.min_retrieval_similarity]
        return recent

    def add(self, obs: FrameObservations):
        """Process one frame; returns (Keyframe or None, [Edge, ...])."""
        self.stats.frames += 1
        if len(obs) < self.config.min_detections:
            self.stats.skipped += 1
            return None, []
        if self._too_soon(obs):                     # before any matching: that is the saving
            return None, []
        # the pose to the last keyframe decides, and is reused as that candidate's edge
        last_rel = (self._plausible(self._relative(self.keyframes[-1].observations, obs),
                                    self.keyframes[-1].observations.stamp_ns, obs.stamp_ns)
                    if self.keyframes else None)
        if not self._is_keyframe(obs, last_rel):
            return None, []
        descriptor = bag_of_objects(obs)
        keyframe = Keyframe(self._next_id, obs, descriptor)
        self._next_id += 1
        edges = []
        cand = self.candidates(descriptor)
        self.stats.last_candidates = [self.keyframes[i].keyframe_id for i in cand]
        last = len(self.keyframes) - 1
        # two verified objects suffice for a recent neighbour only where the motion prior has
        # checked the pose: in an unordered collection "recent" means nothing
        two_objects_from = (max(0, len(self.keyframes) - self.config.recent_keyframes) if self.config.motion_prior
                            else len(self.keyframes))
        others = [i for i in cand if i != last]            # matched in one batch
        batched = dict(zip(others, self.matcher.match_many(obs, [self.keyframes[i].observations for i in others])))
        for i in cand:
            source = self.keyframes[i]
            self.stats.pairs_tested += 1
            rel = last_rel if i == last else self._plausible(
                self._relative(source.observations, obs, batched[i]), source.observations.stamp_ns, obs.stamp_ns)
            if rel is not None and (i >= two_objects_from or len(rel.inliers) >= self.config.min_retrieved_inliers):
                edges.append(Edge(source.keyframe_id, keyframe.keyframe_id, rel))
        n = len(self.keyframes)
        if self._desc_buffer.shape[1] != len(descriptor):          # first keyframe
            self._desc_buffer = np.zeros((64, len(descriptor)))
        elif n == len(self._desc_buffer):
            self._desc_buffer = np.vstack([self._desc_buffer, np.zeros_like(self._desc_buffer)])
        self._desc_buffer[n] = descriptor
        self.keyframes.append(keyframe)
        self.stats.keyframes += 1
        self.stats.edges += len(edges)
        return keyframe, edges
