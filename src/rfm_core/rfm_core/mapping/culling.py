"""Keyframe culling (not in the paper; as ORB-SLAM and RTAB-Map do): a redundant keyframe of
a stream is merged into a neighbour, so that revisits stop growing the map.

An object here is a set of detections linked by the kept edges' verified matches (a track
before merging and the evidence check). A keyframe K is redundant when it sees at least two
objects that other keyframes see too, each of them seen by ``min_views`` keyframes other than
K and still one object without K's detections, and a registered keyframe A that a kept edge
links to K sees at least one of them; or when a keyframe A that sees one of its objects lies
within ``colocated_m`` and ``colocated_deg`` of it (a revisit whose detections did not verify
against the keyframes there; its detections of objects A does not see are dropped) and no
object of the published map rests on K alone; or when it shares no object with any keyframe
(an isolated view of a revisit, with too few detections to verify one) and no object of the
published map rests on it alone, A being the neighbour of its strongest kept edge. Only
keyframes of a stream are culled (frames the view graph followed were tracked against them;
separate photos each keep their view). K is then merged into A (:class:`Merged`): T_A_K from
the current poses, K's detections mapped to A's of the same objects; the mapper carries K's
edges, frames and later messages naming K over to A (:meth:`rfm_core.mapping.mapper.Mapper.update`).
The map's anchor and the ``keep_newest`` newest keyframes are kept (while newer than
``keep_newest_s`` before the newest frame); nothing is solved again.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from rfm_core.geometry import Pose4
from rfm_core.settings import constant

__all__ = ['CullingConfig', 'Merged', 'protected_keyframes', 'redundant_keyframes']


@dataclass(frozen=True)
class CullingConfig:
    min_views: int = constant(3, 'A keyframe is redundant when other keyframes see each of its objects, each '
                              'object by this many', lo=1, hi=1000)
    keep_newest: int = constant(3, 'The newest keyframes (by id) are not culled ...', lo=1, hi=1000)
    keep_newest_s: float = constant(10.0, '... until the camera has gone on this long without a newer one (s, '
                                    'frame stamps; 0: kept for good)', lo=0.0, hi=3600.0)
    colocated_m: float = constant(0.4, 'A keyframe within this distance of another that sees one of its objects '
                                  'is redundant too, when no published object rests on it alone (m; 0: off) ...',
                                  lo=0.0, hi=10.0)
    colocated_deg: float = constant(15.0, '... and within this turn (deg)', lo=0.0, hi=180.0)


@dataclass(frozen=True)
class Merged:
    """A culled keyframe, carried by the keyframe it was merged into."""

    into: int                                #: the keyframe that carries it
    pose: Pose4                              #: T_into_culled (the averaged poses when it was culled)
    stamp_ns: int                            #: the culled keyframe's stamp
    detections: np.ndarray                   #: (N,) its detection index -> ``into``'s (-1: none)

    def then(self, outer: 'Merged') -> 'Merged':
        """This merge followed by ``outer`` (``into`` itself culled into ``outer.into``)."""
        d = np.where(self.detections >= 0, outer.detections[np.maximum(self.detections, 0)], -1)
        return Merged(outer.into, outer.pose @ self.pose, self.stamp_ns, d)


def protected_keyframes(keyframes: dict, poses: dict, newest_stamp_ns: int, config: CullingConfig) -> set:
    """Keyframes never culled now: the map's anchor (the first registered) and the
    ``keep_newest`` newest by id, while newer than ``keep_newest_s`` before the newest frame
    (their edges are still arriving)."""
    ids = sorted(keyframes)
    return {min(poses)} | {k for k in ids[-config.keep_newest:] if config.keep_newest_s <= 0
                           or newest_stamp_ns - keyframes[k].stamp_ns < config.keep_newest_s * 1e9}


def redundant_keyframes(keyframes: dict, poses: dict, active_edges: list, due: list, config: CullingConfig,
                        sole_holders: Callable[[], set]) -> dict:
    """{culled id: :class:`Merged`} of the keyframes in ``due`` (newest first) that are
    redundant (see the module); ``keyframes`` {id: FrameObservations}, ``poses`` {id: Pose4
    T_k_map} (averaged), ``active_edges`` the edges averaging keeps, ``sole_holders()`` the
    keyframes that alone hold an object of the published map (built only when needed)."""
    ids = sorted(keyframes)
    offset = dict(zip(ids, np.cumsum([0] + [len(keyframes[k]) for k in ids[:-1]]).tolist()))
    n = sum(len(f) for f in keyframes.values())
    owner = np.repeat(np.array(ids), [len(keyframes[k]) for k in ids])      # node -> keyframe
    active = active_edges
    pairs = np.array([(offset[e.source] + a, offset[e.target] + b)
                      for e in active for a, b in e.inliers], int).reshape(-1, 2)
    if not len(pairs):
        return {}
    label = connected_components(sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)),
                                 directed=False)[1]
    members: dict = {}                                   # object -> {node}
    for node, c in enumerate(label):
        members.setdefault(int(c), set()).add(node)
    links: dict = {}                                     # object -> [(node, node)] (its matches)
    for a, b in pairs:
        links.setdefault(int(label[a]), []).append((int(a), int(b)))
    # keyframe -> {keyframe a kept edge links it to: (-its strongest weight, that edge's order)}
    linked: dict = {}
    for i, e in enumerate(active):
        for a, b in ((e.source, e.target), (e.target, e.source)):
            best = linked.setdefault(a, {}).get(b)
            if best is None or -e.weight < best[0]:
                linked[a][b] = (-e.weight, i)
    published = None                                     # keyframes that alone hold a published object (lazily)
    culled, anchors, gone = {}, set(), set()
    for k in due:
        if k in anchors:
            continue
        nodes = range(offset[k], offset[k] + len(keyframes[k]))
        node_set = set(nodes)
        seen_by = {c: {int(owner[u]) for u in members[c]} - gone for c in {int(label[v]) for v in nodes}}
        objects = {c for c, seen in seen_by.items() if len(seen) > 1}       # seen by other keyframes too
        views = {c: seen_by[c] - {k} for c in objects}
        if not objects:                                  # a view that shares no object with the map
            published = sole_holders() if published is None else published
            # (a registered keyframe may have no kept edge left: its edges dropped as outliers)
            near = linked.get(k, {})
            into = None if k in published else min(
                (j for j in near if j in poses and j not in gone), key=near.get, default=None)
            if into is not None:
                culled[k] = Merged(into, poses[into] @ poses[k].inverse(), keyframes[k].stamp_ns,
                                   np.full(len(keyframes[k]), -1))
                anchors.add(into)
                gone.add(k)
            continue
        share = {}                                       # K's neighbours (a kept edge) -> objects shared
        for c in objects:
            for j in views[c]:
                if j in poses and j in linked.get(k, ()):
                    share[j] = share.get(j, 0) + 1
        if len(objects) < 2 or any(len(v) < config.min_views for v in views.values()):
            # a keyframe where another already is (a revisit its detections failed to verify)
            near = {j for c in objects for j in views[c]
                    if j in poses and (poses[j] @ poses[k].inverse()).within(config.colocated_m,
                                                                              config.colocated_deg)}
            if not near:
                continue
            published = sole_holders() if published is None else published    # (builds the tracks)
            if k in published:
                continue
            share = {j: sum(j in views[c] for c in objects) for j in near}
        if not share:
            continue
        into = min(share, key=lambda j: (-share[j], float(np.linalg.norm(poses[j].t - poses[k].t))))
        first = {}                                       # object -> into's first detection of it
        for u in range(offset[into], offset[into] + len(keyframes[into])):
            first.setdefault(int(label[u]), u)
        moved = {v: first.get(int(label[v])) for v in nodes}          # K's node -> into's (or None)
        if not all(_connected(members[c] - node_set, links.get(c, ()), moved) for c in objects):
            continue
        detections = np.array([moved[v] - offset[into] if moved[v] is not None and int(label[v]) in objects
                               else -1 for v in nodes], int)
        culled[k] = Merged(into, poses[into] @ poses[k].inverse(), keyframes[k].stamp_ns, detections)
        anchors.add(into)
        gone.add(k)
        for c in objects:                                # K's matches now end at into's detection
            members[c] -= node_set
            links[c] = [(moved.get(a, a), moved.get(b, b)) for a, b in links.get(c, ())
                        if moved.get(a, a) is not None and moved.get(b, b) is not None]
    return culled


def _connected(nodes: set, links, moved: dict) -> bool:
    """Whether ``nodes`` (detections of one object) stay linked by ``links`` (pairs of
    detections) once each detection in ``moved`` is replaced by its value (None: removed)."""
    parent = {v: v for v in nodes}

    def find(v):
        while parent[v] != v:
            parent[v] = parent[parent[v]]
            v = parent[v]
        return v

    for a, b in links:
        a, b = moved.get(a, a), moved.get(b, b)
        if a in parent and b in parent:
            parent[find(a)] = find(b)
    return len({find(v) for v in nodes}) <= 1
