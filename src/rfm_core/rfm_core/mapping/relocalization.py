"""Relocalization against a map (paper appendix): where is a frame, given the map's
registered keyframes and object tracks?

The paper matches the query against candidate keyframes, verifies each relative pose and
takes the keyframe with the most object inliers. Here every keyframe verified with at least
``min_keyframe_inliers`` objects votes for its pose; the pose whose agreeing keyframes
(within pose averaging's outlier thresholds) verify the most distinct query objects wins,
needs ``min_inliers`` of them, is averaged over the agreeing keyframes, and is refitted on
the map's object tracks. Each keyframe's relative pose and the final pose are corrected by
the floor and the walls the query and the keyframe both measured, and the final pose by
their depth points too (as the view graph's edges: ``relative_pose.with_surfaces``). Up to
``hypotheses`` such poses (groups of agreeing keyframes) are then checked against the whole
map: the query's detections placed by each must overlap the map's objects, ``min_explained``
of them (all, for a query with fewer); the pose explaining the most wins. No ROS here; the
mapper (and its node's ``rfm/relocalize`` service, and localization mode) call
:func:`relocalize`.

:func:`match_to_map` matches a view against the map's objects instead of its keyframes (a
view may share objects with the map but with no single keyframe): the mapper's tracking
recovery joins a keyframe that nothing else links to the map with it, only where the camera
can have walked since the map last saw it.
:func:`match_on_points` places a query no keyframe places from the same pose hypotheses,
aligned on its depth points to the map's.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rfm_core.geometry import Pose4, circular_mean, iou_3d_paired, kabsch_4dof, wrap_angle
from rfm_core.mapping.averaging import AveragingConfig, agreement
from rfm_core.mapping.frame_log import camera_to_map
from rfm_core.mapping.map_index import MapIndex, track_boxes
from rfm_core.matching.classical import ClassicalMatcher, ObjectMatches, size_similarity
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.relative_pose import (RelativePose, YawPrior, box_hits, estimate_relative_pose,
                                             pair_hypotheses, track_on_points, with_surfaces)
from rfm_core.observations import FrameObservations
from rfm_core.settings import constant, setting

__all__ = ['RelocalizationConfig', 'Relocalization', 'MotionPrior', 'MapMatch', 'MapIndex', 'relocalize',
           'walking_reach', 'same_view', 'detections_needed', 'match_to_map', 'match_on_points', 'refine_on_tracks',
           'explained', 'track_boxes']


#: two cameras further apart than this see nothing in common (twice a depth camera's reach)
SHARED_VIEW_M = 10.0


@dataclass(frozen=True)
class RelocalizationConfig:
    candidates: int = setting(10, 'Keyframes tried per query (the most similar by bag of objects)', lo=1, hi=1000)
    min_inliers: int = setting(2, 'Query objects the agreeing keyframes must verify; raise it to trade recall for '
                               'fewer wrong poses', lo=1, hi=100,
                               paper='2 (one keyframe verified by the relative-pose test)')
    min_keyframe_inliers: int = constant(2, "Inliers a keyframe's vote needs", lo=1, hi=100)
    min_explained: int = setting(4, "Query detections a pose must place on the map's objects (all of a smaller "
                                 'query, but at least 3): verifies it against the whole map (0: off)', lo=0, hi=100)
    hypotheses: int = constant(3, 'Distinct poses (groups of agreeing keyframes) verified against the map per '
                               'query', lo=1, hi=20)
    recovery_min_inliers: int = constant(3, 'Tracking recovery: objects the edge that joins a keyframe to the map '
                                         'must verify', lo=2, hi=100)
    map_hypotheses: int = constant(5, "Matching a view to the map's objects: distinct poses tried (from single box "
                                   'correspondences, most supported first)', lo=1, hi=50)
    map_yaw_tolerance_deg: float = constant(10.0, '... the yaw a hypothesis proposes is trusted this far (deg)',
                                            lo=0.5, hi=180.0)
    point_hypotheses: int = constant(2, "A query no keyframe places: the map matching's hypotheses aligned on its "
                                     'depth points', lo=1, hi=50)
    distinct_m: float = constant(0.25, 'Two poses of one view are alternatives when their camera centres are this '
                                 'far apart (m) ...', lo=0.01, hi=10.0)
    distinct_deg: float = constant(5.0, '... or their yaws this far (deg)', lo=0.1, hi=180.0)
    map_correspondences: int = constant(24, "Matching a view to the map's objects: tracks each detection is paired "
                                        'with (the most similar of compatible size)', lo=1, hi=10000)
    stream_max_gap_s: float = setting(2.0, 'Localization mode: a track of localized frames lives this long without '
                                      'a pose (s)', lo=0.1, hi=60.0)
    stream_speed_mps: float = setting(1.5, '... the fastest the camera moves between two frames (m/s); also '
                                      'where tracking recovery looks for a keyframe its stream lost', lo=0.0,
                                      hi=100.0)
    stream_turn_dps: float = constant(180.0, '... the fastest it turns where no gyroscope measured the turn (deg/s)',
                                      lo=0.0, hi=3600.0)
    stream_slack_m: float = constant(0.3, '... plus this much: the error of two relocalized poses (m)',
                                     lo=0.0, hi=10.0)
    stream_slack_deg: float = constant(5.0, '... and this much of yaw (deg)', lo=0.0, hi=180.0)
    stream_min_explained: int = constant(4, '... a pose where the track predicts it must explain this many '
                                         'detections in the map (all of a smaller query)', lo=0, hi=100)


@dataclass(frozen=True)
class MotionPrior:
    """Where a frame's camera can be (a localization track's prediction): T_map_view's yaw
    within ``yaw_tolerance`` (rad) of ``yaw``, its centre within ``reach_m`` of ``centre``
    (the last frame's); ``predicted``: where it most likely is (the camera's velocity)."""

    yaw: float
    centre: np.ndarray
    reach_m: float
    yaw_tolerance: float
    predicted: np.ndarray | None = None      #: the centre the camera's velocity predicts (None: ``centre``)

    @property
    def start(self) -> np.ndarray:
        """Where an alignment of the frame starts: the predicted centre, else ``centre``."""
        return self.centre if self.predicted is None else self.predicted

    def admits(self, pose: Pose4) -> bool:
        """Whether ``pose`` (T_view_map) is where the camera can be."""
        t_map_view = pose.inverse()
        return (float(np.linalg.norm(t_map_view.t - self.centre)) <= self.reach_m
                and abs(wrap_angle(t_map_view.yaw - self.yaw)) <= self.yaw_tolerance)


def walking_reach(config: RelocalizationConfig, seconds: float) -> float:
    """How far a camera can have got in ``seconds`` (m): ``stream_speed_mps`` for the time,
    plus ``stream_slack_m`` for the error of the poses it is measured between."""
    return config.stream_slack_m + config.stream_speed_mps * abs(seconds)


@dataclass
class Relocalization:
    pose: Pose4                              #: T_query_map (4-DoF, the query's aligned frame)
    keyframe_id: int                         #: the agreeing keyframe with the most inliers
    num_inliers: int
    inliers: np.ndarray                      #: (K, 2) query index, keyframe index
    candidates: int                          #: keyframes tried
    support: int = 0                         #: inliers of all keyframes agreeing on the pose
    agreeing: int = 1                        #: keyframes agreeing on the pose
    explained: int = 0                       #: query detections the pose places on the map's objects
    runner_up: int = 0                       #: the same for the best distinct alternative pose (0: none)
    covariance: np.ndarray | None = None     #: (6, 6) of the camera pose (Mapper.frame_covariance), once asked

    def camera_to_map(self, query: FrameObservations) -> np.ndarray:
        """4x4 pose of the query's camera optical frame in the map frame."""
        return camera_to_map(self.pose, query.gravity_cam)


def relocalize(query: FrameObservations, index: MapIndex, matcher, config: RelocalizationConfig,
               matching: MatchingConfig, averaging: AveragingConfig, why: list | None = None,
               prior: MotionPrior | None = None) -> Relocalization | None:
    """The query's pose in the map (``index``: :class:`MapIndex`, its tracks built only once a keyframe
    verified a pose), or None (and the reason appended to ``why``). Against keyframes first; a
    query no keyframe places (and no track predicts) is then placed by the map's objects and its
    depth points (:func:`match_on_points`). ``prior`` (a localization track's prediction): only
    poses it admits, and ``stream_min_explained`` detections explained suffice."""
    why = why if why is not None else []
    if len(query) < 2 or not index.poses:
        why.append(f'the query has {len(query)} detections; need >= 2' if index.poses else 'the map has no '
                   'registered keyframes')
        return None
    found = _on_keyframes(query, index, matcher, config, matching, averaging, why, prior)
    if found is None and prior is None:
        found = match_on_points(query, index, matching, config, why)
    return found


def _on_keyframes(query, index: MapIndex, matcher, config, matching, averaging, why, prior=None):
    """:func:`relocalize` against the most similar keyframes."""
    keyframes, poses = index.keyframes, index.poses
    candidates = index.candidates(query, config.candidates)
    if prior is not None:                       # the keyframes where the track predicts the camera, and those
        # retrieved that can see what it sees (a building's other rooms cannot: only cost)
        near = index.keyframes_near(prior.centre, prior.yaw, prior.reach_m, config.candidates)
        candidates = [k for k in candidates if np.linalg.norm(poses[k].inverse().t - prior.centre)
                      <= prior.reach_m + SHARED_VIEW_M] + near
        candidates = list(dict.fromkeys(candidates))
    found = []
    fallback = ClassicalMatcher(matching) if not isinstance(matcher, ClassicalMatcher) else None
    for k, matches in zip(candidates, matcher.match_many(query, [keyframes[k] for k in candidates])):
        rel = estimate_relative_pose(query.boxes, keyframes[k].boxes, matches, matching)
        if (rel is None or len(rel.inliers) < config.min_keyframe_inliers) and fallback is not None:
            rel = estimate_relative_pose(query.boxes, keyframes[k].boxes, fallback.match(query, keyframes[k]), matching)
        if rel is None or len(rel.inliers) < config.min_keyframe_inliers:
            continue
        rel = _with_surfaces(rel, keyframes[k], query, matching, points=False)   # points: the final pose only
        # rel.pose = T_kf_query; T_query_map = T_kf_query^-1 T_kf_map
        pose = rel.pose.inverse() @ poses[k]
        if prior is None or prior.admits(pose):
            found.append((k, rel, pose))
    if not found:
        why.append(f'no candidate keyframe (of {len(candidates)}) verified a relative pose with '
                   f'{config.min_keyframe_inliers} objects' + (' where the track predicts the camera' if prior else ''))
        return None
    # consensus: each verified keyframe votes for its pose; the pose whose agreeing keyframes
    # verify the most distinct query objects wins, averaged over them
    centres = np.array([pose.inverse().t for _, _, pose in found])
    agree = agreement([pose.yaw for _, _, pose in found], centres, averaging)
    support = np.array([len({int(iq) for j in np.flatnonzero(row) for iq in found[j][1].inliers[:, 0]})
                        for row in agree])
    # distinct hypotheses, by support: each a group of agreeing keyframes not in a stronger one
    hypotheses, used = [], np.zeros(len(found), bool)
    for winner in np.argsort(-support, kind='stable'):
        if used[winner] or support[winner] < config.min_inliers or len(hypotheses) >= config.hypotheses:
            continue
        members = np.flatnonzero(agree[winner] & ~used)
        used[members] = True
        best = max(members, key=lambda j: (len(found[j][1].inliers), -found[j][1].mean_error))
        w = np.array([len(found[j][1].inliers) for j in members], float)
        pose = Pose4.from_centre(circular_mean([found[j][2].yaw for j in members], w),
                                 (w[:, None] * centres[members]).sum(0) / w.sum())
        pose = refine_on_tracks(query, pose, [found[j] for j in members], index, matching)
        hypotheses.append((explained(query, pose, index, matching), int(support[winner]), pose, best, members))
    if not hypotheses:
        why.append(f'the verified keyframes agree on no pose with {config.min_inliers} query objects')
        return None
    count, support_, pose, best, members = max(hypotheses, key=lambda h: h[:2])
    need = detections_needed(config, len(query)) if prior is None else min(config.stream_min_explained, len(query))
    if count < need:
        why.append(f'verification against the map failed: the best pose explains {count} of the query\'s '
                   f'{len(query)} detections; need {need}')
        return None
    runner_up = max((h[0] for h in hypotheses if not same_view(h[2].inverse(), pose.inverse(), config)), default=0)
    k, rel, _ = found[best]
    # the floor, walls and depth points again on the final pose: the refit on the tracks' centres moves it
    final = replace(rel, pose=poses[k] @ pose.inverse())                         # T_k_query
    pose = _with_surfaces(final, keyframes[k], query, matching).pose.inverse() @ poses[k]
    pose = on_map_points(query, pose, index, matching, need)
    return Relocalization(pose, k, len(rel.inliers), rel.inliers, len(candidates), support_, len(members), count,
                          runner_up)


def on_map_points(query: FrameObservations, pose: Pose4, index: MapIndex, matching: MatchingConfig,
                  explains: int) -> Pose4:
    """``pose`` (T_query_map) refined on the query's depth points aligned to the map's (every
    registered keyframe's, merged: :meth:`MapIndex.cloud_near`): from the pose, and from it
    at the height the query's floor gives it above the map's (:meth:`MapIndex.floor_under`)
    where that differs; the alignment that fixes every direction and puts the most points on
    the map's surfaces is kept where it moves the pose by at most ``point_max_correction_m`` /
    ``_deg`` and still explains ``explains`` of the query's detections in the map (what a pose
    needs to be accepted). Partial boxes of furniture made of parts place a view decimetres off
    (along the furniture, or up where a part's box was cut at a seat taken for the floor); the
    room's surfaces do not."""
    if not len(query.cloud):
        return pose
    t_map_view = pose.inverse()
    starts = [t_map_view]
    floor = index.floor_under(t_map_view.t)
    if np.isfinite(floor) and np.isfinite(query.camera_height):
        level = np.array(t_map_view.t, float)
        level[2] = floor + query.camera_height
        if abs(level[2] - t_map_view.t[2]) > matching.point_match_m:
            starts.append(Pose4(t_map_view.yaw, level))
    cloud = index.cloud_near(t_map_view.t)
    best = None
    for start in starts:
        a = track_on_points(start, cloud, query, matching)
        if (a is None or a.free or np.linalg.norm(a.pose.t - t_map_view.t) > matching.point_max_correction_m
                or np.degrees(abs(a.pose.angle_to(t_map_view))) > matching.point_max_correction_deg):
            continue
        if best is None or a.overlap > best.overlap:
            best = a
    if best is None:
        return pose
    refined = best.pose.inverse()
    return refined if explained(query, refined, index, matching) >= explains else pose


def detections_needed(config: RelocalizationConfig, detections: int) -> int:
    """Detections a pose found without a track's prior must explain in the whole map
    (``min_explained``): all of a small query's, but never only the two a pose can be built
    from: they verify nothing."""
    return max(min(config.min_explained, detections), min(config.min_explained, 3))


def _with_surfaces(rel: RelativePose, keyframe, query, matching: MatchingConfig, points: bool = True) -> RelativePose:
    """``rel`` (T_keyframe_query, inliers as (query, keyframe) pairs) corrected by the floor,
    the walls and (``points``) the depth points both frames measured, as a view graph edge
    (keyframe as its source)."""
    return with_surfaces(rel.swap_index_order(), keyframe, query, matching, points).swap_index_order()


def explained(query: FrameObservations, pose: Pose4, index: MapIndex, matching: MatchingConfig) -> int:
    """How many of the query's detections ``pose`` (T_query_map) explains: placed in the
    map, each overlaps one of the map's boxes (:func:`track_boxes`: the tracks' boxes and
    their views) by ``matching.inlier_iou``. Only boxes within reach are compared."""
    if not len(query):
        return 0
    moved = pose.inverse().transform_boxes(query.map_boxes)                # in the map
    return int(index.overlapping(moved, matching.inlier_iou).sum())


def refine_on_tracks(query: FrameObservations, pose: Pose4, verified, index: MapIndex,
                     matching: MatchingConfig) -> Pose4:
    """Refit a relocalized pose on the map's object tracks: each query detection matched (as
    a verified inlier) to an observation of a track is paired with the track's centre — the
    median of all its observations lifted into the map, so much less noisy than one
    keyframe's detection — and the 4-DoF pose is refitted on those centres, weighted by range
    like the relative-pose refit. Centres come from the boxes relative poses use
    (``FrameObservations.boxes``: fitted ones where the detector also gives full boxes); the
    refit is kept only when the query's full boxes still verify against the tracks' boxes
    and lie on the map's boxes better than under ``pose`` (the sum of each detection's
    largest IoU): partial boxes' centres move with the viewpoint, so in rooms of furniture made
    of parts a refit on the tracks' centres can turn a right pose wrong. ``verified``: (keyframe
    id, relative pose, T_query_map) of the agreeing keyframes."""
    votes, by_id = {}, {}
    for k, rel, _ in verified:
        for iq, ik in rel.inliers:
            t = index.track_of(k, ik)
            if t is not None:
                votes.setdefault(int(iq), []).append(t.track_id)
                by_id[t.track_id] = t
    pairs = [(iq, by_id[max(set(ids), key=ids.count)]) for iq, ids in votes.items()]
    if len(pairs) < 3:
        return pose
    idx = [iq for iq, _ in pairs]
    q = query.boxes[idx]
    target = np.array([index.centre(t) for _, t in pairs])
    rng = np.linalg.norm(q[:, :3], axis=1)
    w = 1.0 / (matching.refine_sigma_m + matching.refine_sigma_per_m * rng) ** 2
    t_map_q = kabsch_4dof(q[:, :3], target, w)
    moved = t_map_q.transform_boxes(query.map_boxes[idx])
    reps = np.array([t.box for _, t in pairs])
    if np.mean(iou_3d_paired(moved, reps) >= matching.inlier_iou) < matching.min_inlier_ratio:
        return pose
    refit = t_map_q.inverse()
    return refit if _overlap(query, refit, index) > _overlap(query, pose, index) else pose


def _overlap(query: FrameObservations, pose: Pose4, index: MapIndex) -> float:
    """How well ``pose`` (T_query_map) lays the query's detections on the map: the sum over
    them of each one's largest IoU with the map's boxes."""
    return float(index.best_iou(pose.inverse().transform_boxes(query.map_boxes)).sum())


# ---------------------------------------------------------------------- matching to the map


@dataclass
class MapMatch:
    """A view matched against the map's objects (:func:`match_to_map`)."""

    keyframe_id: int                         #: the registered keyframe the edge is measured from
    relative: RelativePose                   #: T_keyframe_view, inliers as (keyframe, view) detection pairs
    pose: Pose4                              #: T_view_map
    explained: int                           #: view detections the pose places on the map's objects
    runner_up: int                           #: the same for the best distinct alternative pose (0: none)
    detections: int = 0                      #: the view's detections
    guided: bool = False                     #: made under a motion prior (the gyroscope's yaw, a walk's reach)

    def accepted(self, config: RelocalizationConfig, whole_map: bool = False) -> bool:
        """Whether to trust the match: verified with ``recovery_min_inliers`` objects against
        a keyframe, explaining ``min_explained`` detections in the whole map and more than any
        alternative pose. A match the gyroscope's yaw and the camera's reach guided is held as
        a localization track's frame is: ``stream_min_explained`` detections explained (all of
        a smaller view), more than any alternative, and verified against a keyframe with
        ``recovery_min_inliers`` objects (all of a smaller view), or ``min_keyframe_inliers``
        once the whole map is solved (``whole_map``: the global pass; the yaw given, one
        object fixes the pose and the other checks it, and the place the view was taken is in
        the map to compete with a look-alike, which a growing map may not have seen yet)."""
        if self.guided:
            inliers = config.min_keyframe_inliers if whole_map else min(config.recovery_min_inliers, self.detections)
            return (len(self.relative.inliers) >= inliers
                    and self.explained >= min(config.stream_min_explained, self.detections)
                    and self.explained > self.runner_up)
        return (len(self.relative.inliers) >= config.recovery_min_inliers and self.explained >= config.min_explained
                and self.explained > self.runner_up)


def match_to_map(query: FrameObservations, index: MapIndex, matching: MatchingConfig, config: RelocalizationConfig,
                 prior: MotionPrior | None = None, why: list | None = None) -> MapMatch | None:
    """Match a view against the map's object tracks rather than one keyframe (its objects may
    be in no single keyframe's view). Each detection's ``config.map_correspondences`` most
    similar tracks of compatible size (:meth:`MapIndex.similar`) propose a pose each
    (T_map_view's yaw from ``prior``, the gyroscope's, or else from the two boxes' yaws up
    to quarter turns; the translation from their centres); with a ``prior`` only the poses it
    admits (where the camera can have got to). The
    ``config.map_hypotheses`` distinct poses that land the most view boxes on tracks are each
    verified with the paper's test against the registered keyframe that saw most of the
    matched tracks, and scored against the whole map (:func:`explained`). The best is returned
    with the best distinct alternative's score; the caller decides (None when nothing
    verifies, the reason in ``why``)."""
    why = why if why is not None else []
    if len(query) < 2 or not index.poses or not index.tracks:
        why.append('fewer than two detections, or no map to match')
        return None
    qb = np.asarray(query.map_boxes, float)
    hypotheses, compatible = _map_hypotheses(query, index, matching, config, prior)
    if hypotheses is None:
        why.append('no detection the size of a mapped object')
        return None
    found = []                                  # (explained, inliers, T_view_map, keyframe, relative)
    for t_map_view in hypotheses:
        result = _verify(query, t_map_view, qb, compatible, index, matching, config)
        if result is not None:
            rel, k = result
            pose = rel.pose.inverse() @ index.poses[k]                       # T_view_k T_k_map
            if prior is None or prior.admits(pose):
                found.append((explained(query, pose, index, matching), len(rel.inliers), pose, k, rel))
    if not found:
        why.append(f'no pose from the map\'s objects verified against a keyframe ({len(hypotheses)} tried'
                   + (', where the camera can be)' if prior is not None else ')'))
        return None
    found.sort(key=lambda f: (-f[0], -f[1]))
    best = found[0]
    runner_up = max((f[0] for f in found[1:] if not same_view(f[2].inverse(), best[2].inverse(), config)), default=0)
    return MapMatch(best[3], best[4], best[2], best[0], runner_up, len(query), prior is not None)


def _map_hypotheses(query: FrameObservations, index: MapIndex, matching: MatchingConfig,
                    config: RelocalizationConfig, prior: MotionPrior | None = None) -> tuple:
    """:func:`match_to_map`'s pose hypotheses (T_map_view), most supported first, at most
    ``config.map_hypotheses`` distinct ones (None: no detection the size of a mapped object),
    and the (query box, track) size compatibility they were found with. With a ``prior``:
    its yaw, and only camera centres within its reach."""
    qb = np.asarray(query.map_boxes, float)
    tb = index.boxes
    ii, jj = index.similar(qb, query.embeddings, matching.size_ratio_gate, config.map_correspondences)
    if not len(ii):
        return None, None
    # the gyroscope's yaw, else the boxes' up to quarter turns; the translations: the camera centres
    hy, trans = pair_hypotheses(qb, tb, ii, jj, None if prior is None else np.full((len(ii), 1), float(prior.yaw)))
    if prior is not None:
        near = np.linalg.norm(trans - prior.centre, axis=1) <= prior.reach_m
        hy, trans = hy[near], trans[near]
        if not len(hy):
            return [], None
    # a hypothesis' support: view boxes landing on the tracks some detection proposed
    play = np.unique(jj)
    compatible = size_similarity(qb, tb) >= matching.size_ratio_gate
    count = np.concatenate([box_hits(qb, tb[play], compatible[:, play], hy[c:c + 256], trans[c:c + 256]).any(2).sum(1)
                            for c in range(0, len(hy), 256)])
    tried = []
    for h in np.argsort(-count, kind='stable'):
        if count[h] < 2 or len(tried) >= config.map_hypotheses:
            break
        t_map_view = Pose4(float(hy[h]), trans[h])
        if not any(same_view(t_map_view, other, config) for other in tried):
            tried.append(t_map_view)
    return tried, compatible


def match_on_points(query: FrameObservations, index: MapIndex, matching: MatchingConfig,
                    config: RelocalizationConfig, why: list | None = None) -> Relocalization | None:
    """A query no keyframe places, placed by the map's objects and its depth points: each of
    :func:`match_to_map`'s pose hypotheses (single box correspondences, most supported first)
    is aligned on the query's depth points to the map's (:meth:`MapIndex.cloud_near`,
    :func:`~rfm_core.matching.relative_pose.track_on_points`); an alignment the points fix in
    every direction is a candidate, scored by the detections it explains (:func:`explained`).
    The best must explain as many as a keyframe's pose must, and more than any distinct
    alternative (None otherwise, and the reason appended to ``why``, except for a query
    without depth points or a map without objects: nothing was tried). Partial boxes of
    plain furniture seen from another walk rarely verify against one keyframe with the
    relative-pose test; the map's surfaces place the view wherever a box correspondence
    brings it near."""
    why = why if why is not None else []
    if not len(query.cloud) or len(query) < 2 or not index.tracks:
        return None                             # nothing to try: the reason stays the keyframes'
    hypotheses = _map_hypotheses(query, index, matching, config)[0] or []
    found = []                                  # (explained, overlap, T_view_map)
    for t_map_view in hypotheses[:config.point_hypotheses]:
        a = track_on_points(t_map_view, index.cloud_near(t_map_view.t), query, matching)
        if a is None or a.free:
            continue
        pose = a.pose.inverse()                                                  # T_view_map
        found.append((explained(query, pose, index, matching), a.overlap, pose))
    if not found:
        why.append(f'no pose from the map\'s objects aligned on the map\'s depth points '
                   f'({min(len(hypotheses), config.point_hypotheses)} tried)')
        return None
    found.sort(key=lambda f: (-f[0], -f[1]))
    count, _, pose = found[0]
    runner_up = max((f[0] for f in found[1:] if not same_view(f[2].inverse(), pose.inverse(), config)), default=0)
    need = detections_needed(config, len(query))
    if count < need or count <= runner_up:
        why.append(f'the map\'s depth points place the query where it explains {count} of its {len(query)} '
                   f'detections (need {need}, and more than the {runner_up} of another pose)')
        return None
    return Relocalization(pose, index.nearest_keyframe(pose.inverse().t), 0, np.zeros((0, 2), int), 0, 0, 0,
                          count, runner_up)


def same_view(a: Pose4, b: Pose4, config: RelocalizationConfig) -> bool:
    """Whether two T_map_view poses are one (centres within ``distinct_m``, yaws within ``distinct_deg``)."""
    return (a.inverse() @ b).within(config.distinct_m, config.distinct_deg)


def _verify(query, t_map_view: Pose4, qb, compatible, index: MapIndex, matching, config):
    """The relative pose of the view to the registered keyframe that saw most of the tracks
    the hypothesis matches (of the three that saw most, the one verified with most inliers):
    (RelativePose T_keyframe_view with (keyframe, view) inliers, keyframe id), or None."""
    tb, keyframes, poses = index.boxes, index.keyframes, index.poses
    hit = box_hits(qb, tb, compatible, np.array([t_map_view.yaw]), t_map_view.t[None])[0]      # (N, M)
    moved = t_map_view.transform_points(qb[:, :3])
    votes = {}
    for n in np.flatnonzero(hit.any(1)):
        cols = np.flatnonzero(hit[n])
        m = cols[np.argmin(np.linalg.norm(moved[n, :2] - tb[cols, :2], axis=1))]
        for k, d in index.observers(m):
            votes.setdefault(k, {}).setdefault(int(n), d)
    best = None
    for k, pairs in sorted(votes.items(), key=lambda kv: -len(kv[1]))[:3]:
        if len(pairs) < max(matching.min_matches, 2):
            continue
        view_idx = np.array(list(pairs), int)
        kf_idx = np.array([pairs[n] for n in view_idx], int)
        guess = poses[k] @ t_map_view                                          # T_k_view
        prior = YawPrior(guess.yaw, np.radians(config.map_yaw_tolerance_deg))
        rel = estimate_relative_pose(query.boxes, keyframes[k].boxes,
                                     ObjectMatches(view_idx, kf_idx, np.ones(len(view_idx))), matching, prior)
        if rel is not None and (best is None or len(rel.inliers) > len(best[0].inliers)):
            best = (rel, k)
    if best is None:
        return None
    rel, k = best                                           # T_k_view, inliers (view, keyframe)
    return rel.swap_index_order(), k
