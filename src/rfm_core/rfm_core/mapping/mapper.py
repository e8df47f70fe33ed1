"""The live mapper: keyframes and view-graph edges in; poses, object tracks and
relocalization out (paper 3.5-3.6 and appendix). No ROS here; the node wraps it.

Keyframe poses are 4-DoF ``T_k_map`` (map frame: gravity-aligned, z up). A keyframe's full
camera pose (optical frame to map) composes that with the keyframe's gravity:
``T_map_cam = T_k_map^-1 * R_aligned_cam``.

Modes: ``mapping`` (keyframes and edges extend the map) and ``localization`` (the map is
frozen; frames are only relocalized). ``posed`` mode takes keyframe poses from outside
(e.g. TF or a pose topic; the paper's "posed" rows) instead of averaging. In mapping mode a
redundant keyframe of a stream is culled: merged into a neighbour that carries its edges and
frames from then on (:mod:`rfm_core.mapping.culling`), and a keyframe outside the registered
map is matched against the map's objects (:mod:`rfm_core.mapping.recovery`).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from rfm_core.clouds import seen_through_both
from rfm_core.geometry import Pose4
from rfm_core.mapping.averaging import AveragingConfig, IncrementalAverager, gyro_drift
from rfm_core.mapping.bundle import BundleConfig, refine_tracks
from rfm_core.mapping.culling import CullingConfig, Merged, protected_keyframes, redundant_keyframes
from rfm_core.mapping.frame_log import FrameLog
from rfm_core.mapping.localization import on_points
from rfm_core.mapping.relocalization import (MapIndex, MotionPrior, Relocalization, RelocalizationConfig,
                                             relocalize, walking_reach)
from rfm_core.mapping.frame_log import camera_to_map as _camera_to_map
from rfm_core.mapping.recovery import TrackingRecovery
from rfm_core.mapping.tracks import TrackConfig, build_tracks
from rfm_core.mapping.uncertainty import frame_covariance, ros_pose_covariance, track_weight
from rfm_core.matching.classical import ClassicalMatcher
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.view_graph import bag_of_objects
from rfm_core.observations import EdgeRecord, FrameObservations, FrameTrack, imu_relative_yaw
from rfm_core.settings import constant, from_dict, section, setting

__all__ = ['MapperConfig', 'CullingConfig', 'RelocalizationConfig', 'EdgeRecord', 'Relocalization', 'Merged', 'Mapper',
           'MODES']

MODES = ('mapping', 'localization')

#: measurements of one keyframe pair kept at most (the first and its repeats, from frames that
#: revisit the pair): the map's edges grow with its keyframes, not with time
MAX_PAIR_MEASUREMENTS = 16
#: edges of fewer objects come only from a stream, its motion prior checking them (the matcher's
#: ``keyframes.min_retrieved_inliers`` elsewhere): never lone (:meth:`Mapper._lone_edges`)
LONE_EDGE_MIN_OBJECTS = 3
#: views whose depth points overlap in fewer points contradict no edge between them (:meth:`Mapper._seen_through`)
MIN_OVERLAP_POINTS = 50


@dataclass(frozen=True)
class MapperConfig:
    averaging: AveragingConfig = section(AveragingConfig, 'pose averaging (paper 3.5)')
    tracks: TrackConfig = section(TrackConfig, 'object tracks (paper 3.6)')
    matching: MatchingConfig = section(MatchingConfig, 'relocalization: object matching and verification '
                                       "(as the matcher's)")
    relocalization: RelocalizationConfig = section(RelocalizationConfig, 'relocalization (paper appendix)')
    posed: bool = constant(False, 'Poses come from outside (set_keyframe_pose; the mapper node: pose_source)')
    bundle_adjustment: bool = setting(False, 'Refine object boxes by partial bundle adjustment against their '
                                      'projected corners (paper 3.6; for RGB-only detectors with good poses)')
    bundle: BundleConfig = section(BundleConfig, 'bundle adjustment')
    culling: CullingConfig = section(CullingConfig, 'keyframe culling (mapping mode)')

    def to_dict(self) -> dict:
        """Every setting, nested by stage (stored in map files)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> 'MapperConfig':
        """From :meth:`to_dict`'s output; settings it lacks keep their defaults, unknown ones
        are ignored (files of other rfm versions). ValueError for a value of the wrong type."""
        return from_dict(cls, values)


def camera_to_map(t_k_map: Pose4, obs: FrameObservations) -> np.ndarray:
    """4x4 pose of a frame's camera optical frame in the map frame."""
    return _camera_to_map(t_k_map, obs.gravity_cam)


class Mapper:
    """Feed :meth:`add_keyframe` / :meth:`add_edge`, call :meth:`update`, read the map."""

    def __init__(self, config: MapperConfig | None = None, matcher=None):
        self.config = config or MapperConfig()
        self.matcher = matcher or ClassicalMatcher(self.config.matching)
        self.reset()

    def reset(self) -> None:
        self.keyframes: dict = {}            # id -> FrameObservations
        self.edges: dict = {}                # (source, target) -> EdgeRecord: the pair's first measurement
        self._pairs: dict = {}               # (source, target) -> every measurement of the pair, in arrival order
        self._averaged: dict = {}            # averager edge index -> EdgeRecord
        self._edges_to: dict = {}            # target -> [(source, target), ...]
        self.averager = IncrementalAverager(self.config.averaging)
        self.averager.lone_edges = self._lone_edges
        self.external_poses: dict = {}       # posed mode: id -> Pose4 T_k_map
        self.mode = 'mapping'
        self.revision = 0
        self._tracks = None
        self._index = None
        self._covariances = None             # the solution's KeyframeCovariances, once asked for
        self._descriptors: dict = {}
        self.frames = FrameLog()             # every localized frame (tracked or relocalized)
        self.origins: dict = {}              # id -> (view-graph session, its keyframe id), where numbered
        self.last_update_seconds = 0.0
        self.recovery = TrackingRecovery()   # tracking recovery's state (keyframes tried)
        self._newest_stamp_ns = -1           # of any keyframe or tracked frame received
        self.recovered: list = []            # edges that joined a keyframe to the map (tracking recovery)
        self.merged: dict = {}               # culled keyframe id -> Merged (keyframe culling)
        self._cull_due: set = set()          # keyframes new edges touched since the last culling pass
        self.carried: dict = {}              # (keyframe, detection) -> views of culled keyframes it stands for
        self.streamed: set = set()           # keyframes that frames of a stream were tracked against
        self.gyro_drift = 0.0                # the gyroscope's yaw drift the edges measure (rad/s)
        self._gyro: dict = {}                # averager edge index -> (gyroscope's yaw, seconds) of its yaw-only edges
        self._spans: dict = {}               # (source, target, their stamps) -> (gyroscope's yaw, seconds) or None
        self._reference_index = (None, None)  # (the loaded map's keyframes, their MapIndex): reference_index

    # ------------------------------------------------------------------ input

    def add_keyframe(self, keyframe_id: int, obs: FrameObservations) -> bool:
        """Add a keyframe; False (ignored) in localization mode or when already known."""
        if self.mode != 'mapping' or keyframe_id in self.keyframes or keyframe_id in self.merged:
            return False
        previous = max(self.keyframes, default=None)
        self.keyframes[keyframe_id] = obs
        self._newest_stamp_ns = max(self._newest_stamp_ns, obs.stamp_ns)
        self._descriptors[keyframe_id] = bag_of_objects(obs)
        if not self.config.posed:
            self.averager.add_keyframe(keyframe_id)
            if previous is not None and previous < keyframe_id:
                self._add_gyroscope_edge(previous, keyframe_id)
        self._changed()
        return True

    def _add_gyroscope_edge(self, source: int, target: int) -> None:
        """The gyroscope's yaw between consecutive keyframes of one integration epoch, as a
        yaw-only edge of weight ``averaging.gyro_yaw_weight`` (pose averaging): an edge from
        boxes whose yaw it contradicts is outvoted and dropped instead of turning the map.
        (A map loaded from a file has no gyroscope readings: its keyframes get none.)"""
        weight = self.config.averaging.gyro_yaw_weight
        span = self._span(source, target) if weight > 0 else None
        if span is not None:
            yaw, seconds = span
            self._gyro[len(self.averager.edges)] = span
            self.averager.add_edge(source, target, Pose4(yaw + self.gyro_drift * seconds, (0.0, 0.0, 0.0)), weight,
                                   yaw_only=True)

    def _span(self, source: int, target: int):
        """(yaw of T_source_target as the gyroscope measured it, seconds between them), or
        None when the two keyframes share no integration epoch (cached)."""
        a, b = self.keyframes[source], self.keyframes[target]
        key = (source, target, a.stamp_ns, b.stamp_ns)
        if key not in self._spans:
            yaw = imu_relative_yaw(a, b)
            self._spans[key] = None if yaw is None else (yaw, (b.stamp_ns - a.stamp_ns) * 1e-9)
        return self._spans[key]

    def _correct_gyroscope(self) -> None:
        """The gyroscope's yaw drift, as the edges of objects and points measure it against
        the gyroscope's yaw between the same keyframes (:func:`~rfm_core.mapping.averaging.gyro_drift`),
        taken out of its yaw-only edges: a drift of a few tenths of a degree a second
        otherwise turns a robot's map by degrees over a minute, against its loop closures."""
        if not self._gyro:
            return
        spans, residuals, weights = [], [], []
        kept = self.averager.edges.active
        for index, edge in self._averaged.items():
            span = self._span(edge.source, edge.target) if kept[index] and edge.source in self.keyframes and \
                edge.target in self.keyframes else None
            if span is not None:
                spans.append(span[1])
                residuals.append(edge.pose.yaw - span[0])            # gyro_drift wraps them
                weights.append(self._weight(edge))
        drift = gyro_drift(spans, residuals, weights, self.config.averaging)
        longest = max(s for _, s in self._gyro.values())
        if abs(drift - self.gyro_drift) * longest < np.radians(self.config.averaging.gyro_drift_update_deg):
            return
        self.gyro_drift = drift
        for index, (yaw, seconds) in self._gyro.items():
            self.averager.set_yaw(index, yaw + drift * seconds)

    def add_edge(self, edge: EdgeRecord) -> bool:
        """Add a verified edge; False when ignored (localization mode, unknown keyframe,
        a loop, a pair measured ``MAX_PAIR_MEASUREMENTS`` times already, a weak edge between
        photos that their depth points contradict (:meth:`_seen_through`), or malformed). A
        pair measured before (a frame revisiting it) adds a repeat measurement: all of them
        vote in pose averaging."""
        if self.mode != 'mapping':
            return False
        for k, col in ((edge.source, 0), (edge.target, 1)):
            size = self._size(k)
            if size is None:
                return False
            if len(edge.inliers) and (edge.inliers[:, col].max() >= size or edge.inliers[:, col].min() < 0):
                raise ValueError(f'edge {(edge.source, edge.target)}: inlier index out of range for keyframe {k}')
        edge = self._resolved(edge)
        key = (edge.source, edge.target)
        if edge.source == edge.target or len(self._pairs.get(key, ())) >= MAX_PAIR_MEASUREMENTS:
            return False
        if key in self.edges and any(e.pose == edge.pose for e in self._pairs[key]):    # the same message again
            return False
        if self._seen_through(edge):
            return False
        self._record(edge)
        self._changed()
        return True

    def _record(self, edge: EdgeRecord) -> None:
        """Keep a measurement between two keyframes of the map and hand it to the averaging."""
        key = (edge.source, edge.target)
        self._cull_due.update(key)
        if key not in self.edges:
            self.edges[key] = edge
            self._edges_to.setdefault(edge.target, []).append(key)
        self._pairs.setdefault(key, []).append(edge)
        if not self.config.posed:
            self._averaged[len(self.averager.edges)] = edge
            self.averager.add_edge(edge.source, edge.target, edge.pose, self._weight(edge))

    def _weight(self, edge: EdgeRecord) -> float:
        """An edge's weight in pose averaging: its objects' (:attr:`EdgeRecord.weight`), or
        ``averaging.points_edge_weight`` where no object verified it (the depth points did)."""
        return edge.weight if len(edge.inliers) else self.config.averaging.points_edge_weight

    def _lone_edges(self) -> np.ndarray:
        """Over the averaging's edges (by the order added): those too weak to join two parts of
        the graph alone (:func:`~rfm_core.mapping.averaging._lone_joins`). An edge between
        keyframes that no stream links (a photo, or the first frame of a segment no frame was
        tracked against) resting on :data:`LONE_EDGE_MIN_OBJECTS` objects or more but fewer
        than ``averaging.lone_join_min_inliers``: nothing checked it, and on photos three
        full boxes give a wrong pose often enough that one such edge turned a whole part of a
        tuning room by 151 deg (docs/design-notes.md). Edges of fewer objects come only from a
        stream, checked by its motion prior."""
        out = np.zeros(len(self.averager.edges), bool)
        for i, edge in self._averaged.items():
            out[i] = self._lone(edge)
        return out

    def _lone(self, edge: EdgeRecord) -> bool:
        """Whether one edge is too weak to join two parts alone (:meth:`_lone_edges`)."""
        return (LONE_EDGE_MIN_OBJECTS <= len(edge.inliers) < self.config.averaging.lone_join_min_inliers
                and not (edge.source in self.streamed and edge.target in self.streamed))

    def _seen_through(self, edge: EdgeRecord) -> bool:
        """Whether the depth points contradict a weak edge between views no stream links
        (fewer than ``averaging.lone_join_min_inliers`` objects): of each view's points moved
        into the other by it (:func:`~rfm_core.clouds.seen_through_both`), more than
        ``averaging.max_seen_through`` lie in space the other saw through. Views overlapping
        in fewer than :data:`MIN_OVERLAP_POINTS` points contradict nothing."""
        cfg = self.config.averaging
        if not 0 < len(edge.inliers) < cfg.lone_join_min_inliers or \
                (edge.source in self.streamed and edge.target in self.streamed):
            return False
        a, b = self.keyframes.get(edge.source), self.keyframes.get(edge.target)
        if a is None or b is None:
            return False
        points, through = seen_through_both(a.cloud, a.rotation_aligned_from_camera, b.cloud,
                                            b.rotation_aligned_from_camera, edge.pose.matrix())
        return points >= MIN_OVERLAP_POINTS and through > cfg.max_seen_through * points

    def _size(self, keyframe_id: int) -> int | None:
        """Detections of a keyframe of the map or of one culled from it (None: unknown)."""
        if keyframe_id in self.keyframes:
            return len(self.keyframes[keyframe_id])
        merged = self.merged.get(keyframe_id)
        return None if merged is None else len(merged.detections)

    def knows(self, keyframe_id: int) -> bool:
        """Whether a keyframe is in the map or was culled into a keyframe of it."""
        return keyframe_id in self.keyframes or keyframe_id in self.merged

    def _resolved(self, edge: EdgeRecord) -> EdgeRecord:
        """The edge between the keyframes of the map that carry its ends (culled keyframes
        replaced by the keyframes they were merged into; matches of detections those do not
        hold are dropped)."""
        ms, mt = self.merged.get(edge.source), self.merged.get(edge.target)
        if ms is None and mt is None:
            return edge
        pose, inliers, corners = edge.pose, np.asarray(edge.inliers, int).reshape(-1, 2), edge.corner_inliers
        inliers, scores, corners = inliers.copy(), np.asarray(edge.scores, float), corners.copy()
        keep, keep_c = np.ones(len(inliers), bool), np.ones(len(corners), bool)
        for m, col, ccol in ((ms, 0, 0), (mt, 1, 2)):
            if m is None:
                continue
            inliers[:, col] = m.detections[inliers[:, col]]
            keep &= inliers[:, col] >= 0
            if len(corners):
                idx = corners[:, ccol].astype(int)
                ok = (idx >= 0) & (idx < len(m.detections))
                corners[ok, ccol] = m.detections[idx[ok]]
                keep_c &= ok & (corners[:, ccol] >= 0)
        if ms is not None:
            pose = ms.pose @ pose
        if mt is not None:
            pose = pose @ mt.pose.inverse()
        return EdgeRecord(ms.into if ms is not None else edge.source, mt.into if mt is not None else edge.target,
                          pose, inliers[keep], scores[keep] if len(scores) == len(keep) else scores,
                          corners[keep_c], edge.score)

    def add_frame(self, track: FrameTrack) -> bool:
        """Log a localized frame (its pose relative to a keyframe); False (ignored) when that
        keyframe id is known with another stamp (an id reused by a restarted matcher)."""
        track = self._resolved_track(track)
        kf = self.keyframes.get(track.keyframe_id)
        if kf is not None and kf.stamp_ns != track.keyframe_stamp_ns:
            return False
        self.frames.add(track)
        if self.averager.pose(track.keyframe_id) is not None:
            self.averager.last_seen = track            # where a part taking over starts
        if track.continuous:
            self.streamed.add(track.keyframe_id)
        self._newest_stamp_ns = max(self._newest_stamp_ns, track.stamp_ns)
        return True

    def _resolved_track(self, track: FrameTrack) -> FrameTrack:
        """A frame tracked against a culled keyframe, relative to the keyframe that carries it."""
        m = self.merged.get(track.keyframe_id)
        if m is None or m.stamp_ns != track.keyframe_stamp_ns:
            return track
        return replace(track, keyframe_id=m.into, keyframe_stamp_ns=self.keyframes[m.into].stamp_ns,
                       pose=m.pose @ track.pose, is_keyframe=False)

    def restore_frames(self, arrays: dict) -> None:
        """Replace the frame log by ``arrays`` (a map file's, validated), and with it which
        keyframes frames of a stream were tracked against (:attr:`streamed`)."""
        self.frames.restore(arrays)
        log = self.frames.arrays()
        stamps = {k: f.stamp_ns for k, f in self.keyframes.items()}
        streamed = zip(log['keyframes'][log['continuous']].tolist(), log['keyframe_stamps'][log['continuous']].tolist())
        carriers = (self.frames.keyframe_of(k, s, stamps, self.merged) for k, s in set(streamed))
        self.streamed = {c[0] for c in carriers if c is not None}

    def awaits_recovery(self, keyframe_id: int) -> bool:
        """Whether tracking recovery has yet to try this keyframe, which is outside the
        registered map (an update tries it once something newer has arrived)."""
        obs = self.keyframes.get(keyframe_id)
        return (self.mode == 'mapping' and not self.config.posed and obs is not None
                and self.recovery.awaits(keyframe_id, obs, self.config.relocalization)
                and self.averager.pose(keyframe_id) is None)

    def frame_pose(self, track: FrameTrack) -> np.ndarray | None:
        """4x4 camera-to-map pose of a tracked frame now (None while its keyframe has none).
        A keyframe that arrived since the last :meth:`update` is placed provisionally by its
        best-supported edge from a registered keyframe."""
        track = self._resolved_track(track)
        k = track.keyframe_id
        kf = self.keyframes.get(k)
        if kf is None or kf.stamp_ns != track.keyframe_stamp_ns:
            return None
        p = self.pose(k)
        if p is None:
            p = self._provisional_pose(k)
            if p is None:
                return None
        return _camera_to_map(track.pose.inverse() @ p, track.gravity_cam)

    def _provisional_pose(self, keyframe_id: int, budget: int = 16) -> Pose4 | None:
        """T_k_map of a not yet averaged keyframe (:meth:`_provisional_chain`)."""
        chain = self._provisional_chain(keyframe_id, budget)
        return None if chain is None else chain[1].inverse() @ self.pose(chain[0])

    def _provisional_chain(self, keyframe_id: int, budget: int = 16):
        """A not yet averaged keyframe chained through its best-supported edges back to a
        registered keyframe (searching at most ``budget`` keyframes): (that keyframe,
        T_keyframe_k, the averaging weights of the chain's edges), or None without one."""
        seen = {keyframe_id}
        # breadth-first back along incoming edges; each entry: (keyframe, T_keyframe_k, weights)
        frontier = [(keyframe_id, Pose4(0.0, (0.0, 0.0, 0.0)), ())]
        while frontier and len(seen) <= budget:
            k, t_k_target, weights = frontier.pop(0)
            incoming = sorted((self.edges[key] for key in self._edges_to.get(k, ())),
                              key=lambda e: -len(e.inliers))
            for e in incoming:
                t_source_target = e.pose @ t_k_target               # T_source_k T_k_target
                chained = weights + (self._weight(e),)
                if self.pose(e.source) is not None:
                    return e.source, t_source_target, chained
                if e.source not in seen:
                    seen.add(e.source)
                    frontier.append((e.source, t_source_target, chained))
        return None

    def relocalized_track(self, obs: FrameObservations, reloc: Relocalization) -> FrameTrack:
        """A relocalized frame as a frame tracked against the keyframe that placed it."""
        k = reloc.keyframe_id
        return FrameTrack(obs.stamp_ns, obs.frame_id, obs.gravity_cam, k, self.keyframes[k].stamp_ns,
                          self.poses[k] @ reloc.pose.inverse(), reloc.num_inliers)

    def keyframe_track(self, keyframe_id: int) -> FrameTrack:
        """A keyframe as a frame tracked against itself."""
        obs = self.keyframes[keyframe_id]
        return FrameTrack(obs.stamp_ns, obs.frame_id, obs.gravity_cam, keyframe_id, obs.stamp_ns,
                          Pose4(0.0, (0.0, 0.0, 0.0)), is_keyframe=True)

    def withheld(self, track: FrameTrack | None) -> bool:
        """Whether ``track``'s pose is not given out: nothing measured enough holds its keyframe.
        A keyframe that is the whole registered map with no edge to any other keyframe: its pose
        is the map's frame by definition, and a part of the view graph that grows without it
        takes the map frame over (a photo collection's first view, often). And a keyframe no
        stream links (a photo) that is not yet averaged, or that the solution holds by one lone
        edge only (:meth:`_lone_edges`; two that agree, or one stronger, hold it): three full
        boxes of two photos give a wrong pose often enough that half the wrong poses published
        on tuning photo collections rested on one such edge (docs/design-notes.md). Its pose
        goes out once a second edge agrees; the saved trajectory has it either way."""
        if track is None or self.config.posed:
            return False
        k = self._resolved_track(track).keyframe_id
        if self.averager.pose(k) is None:
            return k not in self.streamed
        if self.averager.num_registered == 1:
            return track.is_keyframe and not any(k in key for key in self.edges)
        return k not in self.streamed and not self._held_by_evidence(k)

    def _held_by_evidence(self, keyframe_id: int) -> bool:
        """Whether the solution keeps an edge of a registered keyframe that is not lone, or
        lone edges to two other registered keyframes (:meth:`withheld`)."""
        ends = set()
        for j in self.averager.kept_edges_of(keyframe_id):
            edge = self._averaged.get(int(j))
            other = None if edge is None else edge.target if edge.source == keyframe_id else edge.source
            if other is None or self.averager.pose(other) is None:
                continue
            if not self._lone(edge):
                return True
            ends.add(other)
        return len(ends) >= 2

    def frame_covariance(self, track: FrameTrack | None) -> np.ndarray | None:
        """(6, 6) covariance of a tracked frame's camera pose (:meth:`frame_pose`) in the map, in
        geometry_msgs/PoseWithCovariance's order (x, y, z, rotations about x, y, z; see
        :mod:`rfm_core.mapping.uncertainty`); None without a pose (or in posed mode)."""
        if self.config.posed or track is None:
            return None
        track = self._resolved_track(track)
        kf = self.keyframes.get(track.keyframe_id)
        if kf is None or kf.stamp_ns != track.keyframe_stamp_ns:
            return None
        cfg = self.config.averaging
        if self._covariances is None:
            try:
                self._covariances = self.averager.covariances()
            except (RuntimeError, ValueError):       # a singular system: the pose goes out without one
                return None
        covariances = self._covariances
        k, rel = track.keyframe_id, track.pose
        cov_rel = covariances.relative(track_weight(track.num_inliers, track.is_keyframe, cfg.points_edge_weight))
        if self.averager.pose(k) is None:
            chain = self._provisional_chain(k)
            if chain is None:
                return None
            k, t_source_k, weights = chain
            rel = t_source_k @ rel
            cov_rel = cov_rel + sum(covariances.relative(w) for w in weights)
        cov_k = covariances(k)
        if cov_k is None:
            return None
        theta = self.averager.pose(k).yaw
        return ros_pose_covariance(frame_covariance(theta, cov_k, rel, cov_rel),
                                   np.radians(cfg.tilt_sigma_deg)).reshape(6, 6)

    def frame_poses(self) -> dict:
        """{stamp_ns: 4x4 camera-to-map} of every logged frame whose keyframe is registered,
        from the keyframes' current poses."""
        return self.frames.camera_poses(self.poses, {k: f.stamp_ns for k, f in self.keyframes.items()}, self.merged)

    def set_keyframe_pose(self, keyframe_id: int, t_k_map: Pose4) -> None:
        """Posed mode: the keyframe's pose from outside."""
        self.external_poses[keyframe_id] = t_k_map
        self._changed()

    def update(self, force_full: bool = False):
        """Fold new keyframes and edges into the poses; returns the averaging stats."""
        start = time.perf_counter()
        stats = None
        if not self.config.posed:
            self._correct_gyroscope()
            stats = self.averager.update(force_full)
            if self._recover():
                stats = self.averager.update(force_full)
            if force_full and self._place_left_out():
                stats = self.averager.update(force_full)
            if self._cull() and stats.kind == 'none':
                stats.kind = 'local'
            if stats.kind != 'none':
                self.revision += 1
                self._changed()
        else:
            self.revision += 1
        self.last_update_seconds = time.perf_counter() - start
        return stats

    def _recover(self) -> bool:
        """Tracking recovery (:mod:`rfm_core.mapping.recovery`): the edges that join
        keyframes outside the registered map to it; True when one was added."""
        poses = self.averager.poses
        if self.mode != 'mapping' or not poses:
            return False
        found = self.recovery.edges(self.keyframes, poses, self._newest_stamp_ns, self.map_index, self._gyro_prior,
                                    self.config.relocalization, self.config.matching)
        if self.averager.reference:             # a loaded map: keyframes of this session join it
            found += self.recovery.joining_edges(
                self.keyframes, poses, self.edges, self._newest_stamp_ns,
                lambda obs: relocalize(obs, self.reference_index(), self.matcher, self.config.relocalization,
                                       self.config.matching, self.config.averaging),
                self.config.relocalization, self.averager.reference)
            found += self.recovery.on_map_edges(self.keyframes, poses, self.averager.reference, self._on_reference,
                                                self.config.relocalization)
        return self._join(found)

    def _on_reference(self, obs: FrameObservations, prior: MotionPrior) -> Relocalization | None:
        """A keyframe placed on the loaded map where ``prior`` predicts it: on its objects,
        else on its depth points (:mod:`rfm_core.mapping.recovery`)."""
        index, cfg = self.reference_index(), self.config
        found = relocalize(obs, index, self.matcher, cfg.relocalization, cfg.matching, cfg.averaging,
                           prior=prior) if len(obs) >= 2 else None
        return found or on_points(obs, prior, index, cfg.matching)

    def _join(self, edges: list) -> bool:
        """Add the edges that join keyframes to the map (kept in :attr:`recovered`); True when one was new."""
        added = False
        for edge in edges:
            if self.add_edge(edge):
                self.recovered.append(edge)
                added = True
        return added

    def _place_left_out(self) -> bool:
        """The global pass over all poses solved at once (:mod:`rfm_core.mapping.recovery`):
        the keyframes outside the registered map placed against it; True when one joined. Not
        on a loaded map (another session's keyframes join it by two placements that agree)."""
        poses = self.averager.poses
        if self.mode != 'mapping' or not poses or self.averager.reference:
            return False
        return self._join(self.recovery.left_out_edges(
            self.keyframes, poses, self.edges, self.relocalize, self.config.relocalization, self.averager.frame_changes,
            (self.map_index, self._gyro_prior, self.config.matching)))

    def _cull(self) -> bool:
        """Keyframe culling (:mod:`rfm_core.mapping.culling`): each redundant keyframe of a
        stream that new edges touched since the last pass (not a loaded map's) is merged into a
        neighbour (:meth:`_merge`); True when one was."""
        cfg = self.config.culling
        poses = self.averager.poses
        if self.mode != 'mapping' or self.config.posed or len(poses) <= cfg.keep_newest + 1:
            return False
        # a loaded map's keyframes stay as they were saved: a new session's are culled against them
        protected = protected_keyframes(self.keyframes, poses, self._newest_stamp_ns, cfg) | self.averager.reference
        due = sorted((self._cull_due & set(poses) & self.streamed) - protected, reverse=True)
        self._cull_due &= protected
        if not due:
            return False
        culled = redundant_keyframes(self.keyframes, poses, self.active_edges(), due, cfg, self._sole_holders)
        if culled:
            self._merge(culled, poses)
        return bool(culled)

    def _sole_holders(self) -> set:
        """Keyframes that alone hold an object of the published map."""
        return {int(t.observations[0, 0]) for t in self.tracks()
                if np.all(t.observations[:, 0] == t.observations[0, 0])}

    def _merge(self, culled: dict, poses: dict) -> None:
        """Take the ``culled`` keyframes ({id: Merged}) out of the map (see :meth:`_cull`);
        ``poses``: the averaged poses ({id: Pose4 T_k_map}), which the kept keyframes keep."""
        for k, m in list(self.merged.items()):
            if m.into in culled:
                self.merged[k] = m.then(culled[m.into])
        self.merged.update(culled)
        old, store = self._averaged, self.averager.edges
        kept = [(self._resolved(old[i]), bool(store.active[i])) for i in range(len(store)) if i in old]
        for k, m in culled.items():
            # the views of K (and of the keyframes culled into it) stay in the objects' evidence
            for d, into_d in enumerate(m.detections):
                views = 1 + self.carried.pop((k, d), 0)
                if into_d >= 0:
                    key = (m.into, int(into_d))
                    self.carried[key] = self.carried.get(key, 0) + views
            del self.keyframes[k]
            if k in self.streamed:
                self.streamed.discard(k)
                self.streamed.add(m.into)
            self._descriptors.pop(k, None)
            self.recovery.tried.pop(k, None)
        self.edges, self._pairs, self._averaged, self._edges_to = {}, {}, {}, {}
        reference = self.averager.reference    # a loaded map's keyframes, and those they were culled into
        changes, seen = self.averager.frame_changes, self.averager.last_seen
        self.averager, self._gyro = IncrementalAverager(self.config.averaging), {}
        self.averager.lone_edges = self._lone_edges
        self.averager.frame_changes = changes
        self.averager.last_seen = None if seen is None else self._resolved_track(seen)
        self.averager.reference = {k for k in reference if k in self.keyframes} | {
            m.into for k, m in culled.items() if k in reference}
        self.averager.sizes = self.culled_sizes()
        ids = sorted(self.keyframes)
        for i, k in enumerate(ids):
            self.averager.add_keyframe(k)
            if i:
                self._add_gyroscope_edge(ids[i - 1], k)
        active = {}
        for edge, was_active in kept:
            key = (edge.source, edge.target)
            if edge.source == edge.target or len(self._pairs.get(key, ())) >= MAX_PAIR_MEASUREMENTS:
                continue
            active[len(self.averager.edges)] = was_active
            self._record(edge)
        mask = np.array([active.get(i, True) for i in range(len(self.averager.edges))], bool)
        self.averager.restore({k: p for k, p in poses.items() if k in self.keyframes}, mask, fold=False)
        self._changed()

    def culled_sizes(self) -> dict:
        """{keyframe id: keyframes it stands for}: itself and those culled into it, for the
        averaging's choice of the part of the graph that is the map
        (:attr:`~rfm_core.mapping.averaging.IncrementalAverager.sizes`). Culling thins the part
        the camera walks on; without these counts a part it had outgrown took the map frame
        back, and the frame went back and forth."""
        sizes: dict = {}
        for m in self.merged.values():
            sizes[m.into] = sizes.get(m.into, 1) + 1
        return sizes

    def _gyro_prior(self, keyframe_id: int, poses: dict) -> MotionPrior | None:
        """Where keyframe ``keyframe_id`` can be, through the registered keyframe nearest in
        time that shares its integration epoch (None without one): T_map_k's yaw as the
        gyroscope gives it (its drift taken out), the camera within what it can walk in the
        time between them (``relocalization.stream_speed_mps``, ``stream_slack_m``) of that
        keyframe."""
        obs, cfg = self.keyframes[keyframe_id], self.config.relocalization
        for k in sorted(poses, key=lambda k: abs(self.keyframes[k].stamp_ns - obs.stamp_ns)):
            span = self._span(k, keyframe_id)                                  # of T_r_k
            if span is not None:
                yaw = span[0] + self.gyro_drift * span[1]
                yaw_map_k = (Pose4(yaw, (0.0, 0.0, 0.0)).inverse() @ poses[k]).inverse().yaw
                return MotionPrior(float(yaw_map_k), poses[k].inverse().t.copy(), walking_reach(cfg, span[1]),
                                   math.radians(cfg.map_yaw_tolerance_deg))
        return None

    # ------------------------------------------------------------------ output

    def pose(self, keyframe_id: int) -> Pose4 | None:
        """Pose4 T_k_map of one registered keyframe (None if it has none)."""
        if self.config.posed:
            return self.external_poses.get(keyframe_id) if keyframe_id in self.keyframes else None
        return self.averager.pose(keyframe_id)

    @property
    def poses(self) -> dict:
        """{keyframe id: Pose4 T_k_map} of the registered keyframes."""
        if self.config.posed:
            return {k: p for k, p in self.external_poses.items() if k in self.keyframes}
        return self.averager.poses

    def camera_poses(self) -> dict:
        """{keyframe id: 4x4 camera optical frame -> map} of the registered keyframes."""
        return {k: camera_to_map(p, self.keyframes[k]) for k, p in self.poses.items()}

    def num_components(self) -> int:
        """Connected components of the keyframes over the kept edges."""
        ids = sorted(self.keyframes)
        if not ids:
            return 0
        index = {k: i for i, k in enumerate(ids)}
        edges = [(index[e.source], index[e.target]) for e in self.active_edges()]
        src = [s for s, _ in edges]
        dst = [t for _, t in edges]
        graph = sp.coo_matrix((np.ones(len(src)), (src, dst)), shape=(len(ids), len(ids)))
        return int(connected_components(graph, directed=False)[0])

    def measurements(self) -> list:
        """Every edge measurement, pair by pair (each pair's first, then its repeats)."""
        return [e for measured in self._pairs.values() for e in measured]

    @property
    def repeats(self) -> list:
        """The pairs' measurements after their first (frames that revisited them)."""
        return [e for measured in self._pairs.values() for e in measured[1:]]

    def active_edges(self) -> list:
        """The edge measurements the current solution keeps."""
        if self.config.posed:
            return self.measurements()
        e = self.averager.edges
        return [self._averaged[i] for i in np.flatnonzero(e.active & ~e.yaw_only) if i in self._averaged]

    def restore(self, poses: dict, kept: list) -> None:
        """Set the solution without solving (a map file's): ``poses`` {id: Pose4 T_k_map},
        ``kept`` the added edge measurements it keeps."""
        if self.config.posed:
            for k, p in poses.items():
                self.set_keyframe_pose(k, p)
            return
        kept = {id(e) for e in kept}
        mask = np.zeros(len(self.averager.edges), bool)
        for i, e in self._averaged.items():
            mask[i] = id(e) in kept
        self.averager.restore(poses, mask)
        self._covariances = None

    def _changed(self) -> None:
        """The map changed: its tracks, index and covariances are rebuilt when next needed."""
        self._tracks = None
        self._index = None
        self._covariances = None

    def reference_index(self) -> MapIndex:
        """The loaded map alone (:attr:`IncrementalAverager.reference`: its keyframes are held
        where they were saved), indexed for relocalization; built once per reference."""
        reference = frozenset(k for k in self.averager.reference if k in self.keyframes)
        if self._reference_index[0] != reference:
            poses = {k: p for k, p in self.poses.items() if k in reference}
            self._reference_index = (reference, MapIndex(self.keyframes, poses, self._descriptors,
                                                         lambda: self._object_tracks(poses)))
        return self._reference_index[1]

    def map_index(self) -> MapIndex:
        """The current map indexed for relocalization (cached until the map changes)."""
        if self._index is None:
            self._index = MapIndex(self.keyframes, dict(self.poses), self._descriptors, self.tracks)
        return self._index

    def tracks(self) -> list:
        """Object tracks of the current map (cached until the map changes)."""
        if self._tracks is None:
            tracks = self._object_tracks(self.poses)
            if self.config.bundle_adjustment:
                tracks = refine_tracks(tracks, self.keyframes, self.poses, self.config.bundle)
            self._tracks = tracks
        return self._tracks

    def _object_tracks(self, poses: dict) -> list:
        """Object tracks (paper 3.6) of the keyframes registered in ``poses``, from the kept
        edges' verified matches."""
        matches = [(e.source, int(ia), e.target, int(ib)) for e in self.active_edges() for ia, ib in e.inliers]
        return build_tracks(self.keyframes, poses, matches, self.config.tracks, self.carried)

    # ------------------------------------------------------------------ relocalization

    def relocalize(self, query: FrameObservations, why: list | None = None,
                   prior: MotionPrior | None = None) -> Relocalization | None:
        """The paper's procedure, made more robust: match the query against registered
        keyframes (the ``relocalization.candidates`` most similar by bag-of-objects
        descriptor) and verify each relative pose. The paper takes the keyframe with the most
        object inliers; here every keyframe verified with at least
        ``relocalization.min_keyframe_inliers`` objects votes for its pose; the pose whose
        agreeing keyframes (within the averaging outlier thresholds) verify the most distinct
        query objects wins, needs ``relocalization.min_inliers`` of them, is averaged over
        the agreeing keyframes and refitted on the map's tracks where that lays the query on
        the map better. Looked up in :meth:`map_index`. ``keyframe_id`` is the agreeing
        keyframe with the most inliers. ``prior``: a localization track's prediction
        (:mod:`rfm_core.mapping.localization`)."""
        return relocalize(query, self.map_index(), self.matcher, self.config.relocalization, self.config.matching,
                          self.config.averaging, why, prior)

