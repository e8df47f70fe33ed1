"""Tracking recovery (not in the paper): a keyframe outside the registered map (tracking
lost, a view that matched no keyframe) is matched against the map's objects, so that a lost
track goes on in the map instead of starting a component that nothing joins.

Each such keyframe with enough detections is matched (:func:`~rfm_core.mapping.
relocalization.match_to_map`: every box correspondence with the map's objects proposes a pose
under the gyroscope's yaw through the nearest registered keyframe of its integration epoch,
within what the camera can walk from that keyframe in the time between them)
once a keyframe or frame newer than it has arrived, and again whenever the registered map
has doubled since; a match it accepts (:meth:`~rfm_core.mapping.relocalization.MapMatch.
accepted`) gives the edge that joins it. Not before something newer: the keyframe's own
edges come just after it on another topic, and matching it first made the map depend on the
messages' timing. A keyframe the gyroscope does not link to the map (another integration
epoch: separate photos, no IMU) is not tried: box pairs alone propose wrong yaws.

**Joining another session.** A keyframe of another session (a loaded map's keyframes have
no gyroscope readings, and a new session's gyroscope is not the old one's) is placed
instead as a relocalization query is (:func:`~rfm_core.mapping.relocalization.relocalize`:
keyframes voting, the pose verified against the whole map), once, if it has the three
detections such a query needs; it joins only when
another keyframe of its component was placed too and the two placements agree with the
session's own relative pose between them (its edges composed; within ``distinct_m`` /
``distinct_deg``), as a localization stream confirms a pose by a later frame: one
look-alike placement is common, two that agree with the session's own edges are not. Each
placement that agrees with another of its session's (also after the session joined) gets
the edge from the map keyframe that placed it, so many placements average out the errors of
the first two.

**A joined session goes on on the map.** Once a session has joined, each of its keyframes
registered through its own edges is placed once on the loaded map where its pose predicts
it, as a localization track places a frame (:mod:`rfm_core.mapping.localization`: only
poses within ``stream_slack_m`` / ``stream_slack_deg`` of the prediction, on its objects,
else on its depth points against the map's surfaces), and gets the edge from the map
keyframe that placed it. Without it a session's keyframes that see two or three objects
chain on their own edges, and the chain drifts from the map it joined (0.3 m after ten
keyframes); the map's own objects and surfaces hold it, as in localization mode.

**The views left out, again** (the paper's global pass over a finished capture, 3.5: pose
averaging over the whole view graph, then the views left out registered again). When all
poses are solved at once (the input idle, or the capture finished), every keyframe still
outside the registered map is placed as a relocalization query is (keyframes voting, the
pose verified against the whole map), whatever its gyroscope: a photo of a collection has
no stream to be recovered into. A placement joins it (the edge from the map keyframe that
placed it) when the map's keyframes verified it independently (two keyframes agree on it,
or one verified ``recovery_min_inliers`` objects: one keyframe's two objects are often a
look-alike, and the map's depth points alone joined a part 5 m off on a tuning walk) and it
is unambiguous: no distinct pose explains as many of its detections
(:attr:`~rfm_core.mapping.relocalization.Relocalization.runner_up`), as a map match is
accepted. A placement too weak for that joins too where another keyframe of its part (the
keyframes outside the map that edges link) was placed where the part's own edges put it,
as another session joins a loaded map: two look-alike placements that agree with the
part's edges are rare. Placements made before the map changed its frame confirm nothing. A
keyframe no placement joins that the gyroscope links to the map (one integration epoch) is
matched again under the gyroscope's yaw, as tracking recovery matches it, where two objects
verified suffice: the map has grown since recovery tried it, and now holds the place the view
was taken to compete with a look-alike.
Each keyframe is tried again whenever the registered map has doubled since
(docs/design-notes.md).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from rfm_core.geometry import Pose4
from rfm_core.mapping.relocalization import (MapIndex, MotionPrior, Relocalization, RelocalizationConfig,
                                             detections_needed, match_to_map)
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.view_graph import Edge
from rfm_core.observations import EdgeRecord, FrameObservations

__all__ = ['TrackingRecovery']


class TrackingRecovery:
    """Which keyframes recovery has tried, and the edges it finds (see the module)."""

    def __init__(self):
        self.tried: dict = {}                # keyframe id -> registered keyframes when it was last matched
        self.placed: dict = {}               # another session's keyframe id -> its Relocalization (None: none)
        self.joined: set = set()             # ... those whose placement became an edge
        self.left_out: dict = {}             # keyframe id -> registered keyframes when the global pass tried it
        self.left_out_placed: dict = {}      # ... -> (the map's frame epoch then, its Relocalization or None)
        self.confirmed: set = set()          # ... those whose placement became an edge
        self.on_map: set = set()             # a joined session's keyframes tried on the loaded map

    @staticmethod
    def recoverable(obs: FrameObservations, config: RelocalizationConfig) -> bool:
        """Whether a keyframe has enough detections to be matched to the map under the
        gyroscope's yaw (:meth:`~rfm_core.mapping.relocalization.MapMatch.accepted`)."""
        return len(obs) >= max(config.min_keyframe_inliers, 2)

    @staticmethod
    def placeable(obs: FrameObservations, config: RelocalizationConfig) -> bool:
        """Whether relocalization could place a keyframe on its own: it has the detections a
        pose must explain (:func:`~rfm_core.mapping.relocalization.detections_needed`)."""
        return len(obs) >= max(detections_needed(config, len(obs)), 2)

    def awaits(self, keyframe_id: int, obs: FrameObservations, config: RelocalizationConfig) -> bool:
        """Whether an unregistered keyframe has yet to be tried."""
        return self.recoverable(obs, config) and keyframe_id not in self.tried

    def edges(self, keyframes: dict, poses: dict, newest_stamp_ns: int, index: Callable[[], MapIndex],
              gyro_prior: Callable[[int, dict], MotionPrior | None], config: RelocalizationConfig,
              matching: MatchingConfig) -> list:
        """The edges that join keyframes outside the registered map to it (see the module):
        ``keyframes`` {id: FrameObservations}, ``poses`` the registered ones' {id: Pose4},
        ``index()`` the map indexed for relocalization, ``gyro_prior(id, poses)`` where a
        keyframe can be (T_map_k's yaw as the gyroscope gives it, its centre within what the
        camera can walk from the map keyframe nearest in time of its integration epoch; None
        without one)."""
        due = []
        for k, obs in keyframes.items():
            if (k in poses or not self.recoverable(obs, config) or obs.stamp_ns >= newest_stamp_ns
                    or len(poses) < 2 * self.tried.get(k, len(poses) / 2)):
                continue
            self.tried[k] = len(poses)
            prior = gyro_prior(k, poses)
            if prior is not None:
                due.append((k, prior))
        mapped = index() if due else None
        found = [_guided_edge(keyframes[k], k, mapped, prior, config, matching) for k, prior in due]
        return [edge for edge in found if edge is not None]

    def joining_edges(self, keyframes: dict, poses: dict, edges: dict, newest_stamp_ns: int,
                      relocalize: Callable[[FrameObservations], Relocalization | None],
                      config: RelocalizationConfig, reference: set) -> list:
        """The edges that join keyframes of another session to the map, ``reference`` (the
        loaded map's keyframes), see the module: ``edges`` the map's {(source, target):
        EdgeRecord} (T_source_target), ``relocalize`` a keyframe's placement in the registered
        map (or None). Every placement that agrees with another of its session's gets its
        edge, also once the session has joined: each adds evidence, so the first two
        placements' errors do not carry the whole session."""
        for k, obs in keyframes.items():
            if (k not in reference and k not in self.placed and self.placeable(obs, config)
                    and obs.stamp_ns < newest_stamp_ns):
                found = relocalize(obs)
                self.placed[k] = found
        placed = {k: found for k, found in self.placed.items() if found is not None and k in keyframes}
        out = []
        for a in _confirmed(placed, _session_links(edges, reference) if placed else {}, config, self.joined):
            self.joined.add(a)
            out.append(_edge_from(placed[a], a, poses))
        return out

    def on_map_edges(self, keyframes: dict, poses: dict, reference: set,
                     place: Callable[[FrameObservations, MotionPrior], Relocalization | None],
                     config: RelocalizationConfig) -> list:
        """The edges that hold a joined session on the loaded map (see the module): each
        registered keyframe outside ``reference`` that its own placement did not join,
        ``place``d once where its pose (``poses``: {id: T_k_map}) predicts it."""
        if not self.joined:
            return []
        found = []
        for k, obs in keyframes.items():
            if k in reference or k not in poses or k in self.joined or k in self.on_map:
                continue
            self.on_map.add(k)
            t_map_k = poses[k].inverse()
            prior = MotionPrior(float(t_map_k.yaw), t_map_k.t.copy(), config.stream_slack_m,
                                math.radians(config.stream_slack_deg))
            placed = place(obs, prior)
            if placed is not None:
                found.append(_edge_from(placed, k, poses))
        return found

    def left_out_edges(self, keyframes: dict, poses: dict, edges: dict,
                       relocalize: Callable[[FrameObservations], Relocalization | None],
                       config: RelocalizationConfig, epoch: int = 0, guided=None) -> list:
        """The global pass's edges (see the module): each keyframe of ``keyframes`` outside
        ``poses`` (the registered ones' {id: Pose4}) with enough detections, not tried since
        the map last doubled, placed by ``relocalize``; the unambiguous placements' edges, and
        those of placements another keyframe of their part confirms (``edges``: the map's
        {(source, target): EdgeRecord}). ``epoch`` counts the map's changes of frame: a
        placement made in another frame confirms nothing. ``guided``: (index, gyro_prior,
        matching), as :meth:`edges` takes them: a keyframe the gyroscope links to the map is
        also matched under its yaw, as tracking recovery matches it."""
        found, due = [], []
        for k, obs in keyframes.items():
            if (k in poses or not self.recoverable(obs, config)
                    or len(poses) < 2 * self.left_out.get(k, len(poses) / 2)):
                continue
            self.left_out[k] = len(poses)
            if len(obs) >= max(config.min_explained, 2):
                placed = relocalize(obs)
                self.left_out_placed[k] = (epoch, placed)
                if (placed is not None and placed.explained > placed.runner_up
                        and (placed.agreeing >= 2 or placed.num_inliers >= config.recovery_min_inliers)):
                    found.append(_edge_from(placed, k, poses))
                    self.confirmed.add(k)
                    continue
            if guided is not None:
                due.append(k)
        if due:
            index, gyro_prior, matching = guided
            mapped = index()
            for k in due:
                prior = gyro_prior(k, poses)
                edge = (_guided_edge(keyframes[k], k, mapped, prior, config, matching, whole_map=True)
                        if prior is not None else None)
                if edge is not None:
                    found.append(edge)
                    self.confirmed.add(k)
        placed = {k: found for k, (e, found) in self.left_out_placed.items()
                  if e == epoch and found is not None and k in keyframes and k not in poses
                  and found.keyframe_id in poses}
        for a in _confirmed(placed, _session_links(edges, set(poses)) if placed else {}, config, self.confirmed):
            self.confirmed.add(a)
            found.append(_edge_from(placed[a], a, poses))
        return found


def _guided_edge(obs: FrameObservations, k: int, index: MapIndex, prior: MotionPrior, config: RelocalizationConfig,
                 matching: MatchingConfig, whole_map: bool = False) -> EdgeRecord | None:
    """The edge that joins keyframe ``k`` to the map where matching it to the map's objects
    under ``prior`` (the gyroscope's yaw, the camera's reach) gives a match to trust
    (:meth:`~rfm_core.mapping.relocalization.MapMatch.accepted`, ``whole_map``: the global pass)."""
    match = match_to_map(obs, index, matching, config, prior)
    if match is None or not match.accepted(config, whole_map):
        return None
    return EdgeRecord.from_edge(Edge(match.keyframe_id, k, match.relative))


def _session_links(edges: dict, reference: set) -> dict:
    """{k: [(j, T_j_k), ...]}: the edges ({(source, target): EdgeRecord}, T_source_target)
    between keyframes outside ``reference`` (a new session's), both ways."""
    links: dict = {}
    for (s, t), edge in edges.items():
        if s not in reference and t not in reference:
            links.setdefault(s, []).append((t, edge.pose.inverse()))            # T_t_s
            links.setdefault(t, []).append((s, edge.pose))                      # T_s_t
    return links


def _confirmed(placed: dict, links: dict, config: RelocalizationConfig, skip=frozenset()) -> list:
    """The keyframes of ``placed`` ({k: Relocalization}) outside ``skip`` whose placement
    another of their part confirms: the part's own edges (``links``, :func:`_session_links`)
    carry it to that keyframe's within ``distinct_m`` / ``distinct_deg``."""
    out = []
    for a in placed:
        if a in skip:
            continue
        chain = _session_frame(a, links)                            # T_k_a of a's part
        for b in placed:
            if b == a or b not in chain:
                continue
            predicted = chain[b] @ placed[a].pose                  # T_b_map = T_b_a T_a_map
            if (predicted @ placed[b].pose.inverse()).within(config.distinct_m, config.distinct_deg):
                out.append(a)
                break
    return out


def _session_frame(a: int, links: dict) -> dict:
    """{k: T_k_a} of the keyframes ``links`` (:func:`_session_links`) join to ``a``, composed
    along a breadth-first tree."""
    out, frontier = {a: Pose4(0.0, (0.0, 0.0, 0.0))}, [a]
    while frontier:
        k = frontier.pop(0)
        for j, t_j_k in links.get(k, ()):
            if j not in out:
                out[j] = t_j_k @ out[k]                                         # T_j_a = T_j_k T_k_a
                frontier.append(j)
    return out


def _edge_from(found: Relocalization, k: int, poses: dict) -> EdgeRecord:
    """The edge from the map keyframe that placed keyframe ``k`` to it: T_m_k = T_m_map T_k_map^-1,
    its inliers as (map keyframe, k) detection pairs."""
    m = found.keyframe_id
    inliers = np.asarray(found.inliers, int).reshape(-1, 2)[:, ::-1]
    return EdgeRecord(m, k, poses[m] @ found.pose.inverse(), inliers, np.ones(len(inliers)),
                      np.zeros((0, 5)), 1.0)
