"""Relocalization against a map (paper appendix): where is a frame, given the map's
registered keyframes and object tracks?

The paper matches the query against candidate keyframes, verifies each relative pose and
takes the keyframe with the most object inliers. Here every keyframe verified with at least
``min_keyframe_inliers`` objects votes for its pose; the pose whose agreeing keyframes
(within pose averaging's outlier thresholds) verify the most distinct query objects wins,
needs ``min_inliers`` of them, is averaged over the agreeing keyframes, and is refitted on
the map's object tracks. Up to ``hypotheses`` such poses (groups of agreeing keyframes) are
then checked against the whole map: the query's detections placed by each must overlap the
map's objects, ``min_explained`` of them (all, for a query with fewer); the pose explaining
the most wins. No ROS here; the mapper (and its node's ``rfm/relocalize``
service, and localization mode) call :func:`relocalize`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rfm_core.geometry import Pose4, circular_mean, iou_3d_paired, kabsch_4dof
from rfm_core.mapping.averaging import AveragingConfig, agreement
from rfm_core.mapping.frame_log import camera_to_map
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.relative_pose import estimate_relative_pose
from rfm_core.matching.view_graph import bag_of_objects
from rfm_core.observations import FrameObservations
from rfm_core.settings import setting

__all__ = ['RelocalizationConfig', 'Relocalization', 'relocalize', 'refine_on_tracks', 'explained', 'track_boxes']


@dataclass(frozen=True)
class RelocalizationConfig:
    candidates: int = setting(10, 'Keyframes tried per relocalization query (most similar by bag of objects)',
                              lo=1, hi=1000)
    min_inliers: int = setting(2, 'Query objects the agreeing keyframes must verify; raise it to trade recall '
                               'for fewer wrong poses', lo=1, hi=100,
                               paper='2 (one keyframe verified by the relative-pose test)')
    min_keyframe_inliers: int = setting(2, "A keyframe's vote needs this many inliers", lo=1, hi=100)
    min_explained: int = setting(4, "Query detections the pose must explain in the map (all of them, for a query "
                                 "with fewer): placed by it, each overlapping one of the map's objects (its box or a "
                                 "view of it) with the relative pose test's IoU. Verifies the pose against the whole "
                                 "map, not only the matched keyframes: a wrong pose from look-alike furniture "
                                 "explains its two or three matches and little else (BENCHMARKS.md); 0: off",
                                 lo=0, hi=100)
    hypotheses: int = setting(3, 'Distinct poses (groups of agreeing keyframes, by support) verified against the '
                              'map per query; the one explaining the most detections wins', lo=1, hi=20)


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

    def camera_to_map(self, query: FrameObservations) -> np.ndarray:
        """4x4 pose of the query's camera optical frame in the map frame."""
        return camera_to_map(self.pose, query.gravity_cam)


def _candidates(query, keyframes: dict, poses: dict, descriptors: dict, count: int) -> list:
    """Registered keyframes most similar to the query by bag of objects (the latest ones when
    descriptors are missing or of another size)."""
    ids = [k for k in poses if descriptors.get(k) is not None and len(keyframes[k]) >= 2]
    desc = bag_of_objects(query)
    if np.any(desc) and ids and all(descriptors[k].size == desc.size for k in ids):
        sims = np.array([descriptors[k] @ desc for k in ids])
        return [ids[i] for i in np.argsort(-sims)[:count]]
    return ids[-count:]


def relocalize(query: FrameObservations, keyframes: dict, poses: dict, descriptors: dict, tracks, matcher,
               config: RelocalizationConfig, matching: MatchingConfig,
               averaging: AveragingConfig, why: list | None = None) -> Relocalization | None:
    """The query's pose in the map, or None (and the reason appended to ``why``).
    ``keyframes``: id -> FrameObservations; ``poses``: id -> T_k_map of the registered ones;
    ``descriptors``: id -> bag of objects; ``tracks``: a callable giving the map's object
    tracks (only built once a keyframe verified a pose)."""
    why = why if why is not None else []
    if len(query) < 2 or not poses:
        why.append(f'the query has {len(query)} detections; need >= 2' if poses else 'the map has no registered '
                   'keyframes')
        return None
    candidates = _candidates(query, keyframes, poses, descriptors, config.candidates)
    found = []
    for k in candidates:
        rel = estimate_relative_pose(query.boxes, keyframes[k].boxes, matcher.match(query, keyframes[k]), matching)
        if rel is None or len(rel.inliers) < config.min_keyframe_inliers:
            continue
        # rel.pose = T_kf_query; T_query_map = T_kf_query^-1 T_kf_map
        found.append((k, rel, rel.pose.inverse() @ poses[k]))
    if not found:
        why.append(f'no candidate keyframe (of {len(candidates)}) verified a relative pose with '
                   f'{config.min_keyframe_inliers} objects')
        return None
    # consensus: each verified keyframe votes for its pose; the pose whose agreeing keyframes
    # verify the most distinct query objects wins, averaged over them
    centres = np.array([pose.inverse().t for _, _, pose in found])
    agree = agreement([pose.yaw for _, _, pose in found], centres, averaging)
    support = np.array([len({int(iq) for j in np.flatnonzero(row) for iq in found[j][1].inliers[:, 0]})
                        for row in agree])
    # distinct hypotheses, by support: each a group of agreeing keyframes not in a stronger one
    hypotheses, used, mapped = [], np.zeros(len(found), bool), tracks()
    targets = track_boxes(mapped)
    for winner in np.argsort(-support, kind='stable'):
        if used[winner] or support[winner] < config.min_inliers or len(hypotheses) >= config.hypotheses:
            continue
        members = np.flatnonzero(agree[winner] & ~used)
        used[members] = True
        best = max(members, key=lambda j: (len(found[j][1].inliers), -found[j][1].mean_error))
        w = np.array([len(found[j][1].inliers) for j in members], float)
        pose = Pose4.from_centre(circular_mean([found[j][2].yaw for j in members], w),
                                 (w[:, None] * centres[members]).sum(0) / w.sum())
        pose = refine_on_tracks(query, pose, [found[j] for j in members], mapped, matching, keyframes, poses)
        hypotheses.append((explained(query, pose, targets, matching), int(support[winner]), pose, best, members))
    if not hypotheses:
        why.append(f'the verified keyframes agree on no pose with {config.min_inliers} query objects')
        return None
    count, support_, pose, best, members = max(hypotheses, key=lambda h: h[:2])
    if count < min(config.min_explained, len(query)):
        why.append(f'verification against the map failed: the best pose explains {count} of the query\'s '
                   f'{len(query)} detections; need {min(config.min_explained, len(query))}')
        return None
    k, rel, _ = found[best]
    return Relocalization(pose, k, len(rel.inliers), rel.inliers, len(candidates), support_, len(members), count)


def track_boxes(tracks: list) -> np.ndarray:
    """(M, 7) the map's object boxes a query is checked against: every track's box and its
    views lifted into the map."""
    if not tracks:
        return np.zeros((0, 7))
    return np.concatenate([t.boxes for t in tracks] + [np.array([t.box for t in tracks])])


def explained(query: FrameObservations, pose: Pose4, targets: np.ndarray, matching: MatchingConfig) -> int:
    """How many of the query's detections ``pose`` (T_query_map) explains: placed in the
    map, each overlaps one of ``targets`` (:func:`track_boxes`) by ``matching.inlier_iou``.
    Only boxes within reach are compared."""
    if not len(targets) or not len(query):
        return 0
    moved = pose.inverse().transform_boxes(query.map_boxes)                # in the map
    reach = 0.5 * (np.linalg.norm(moved[:, None, 3:6], axis=-1) + np.linalg.norm(targets[None, :, 3:6], axis=-1))
    near = np.linalg.norm(moved[:, None, :3] - targets[None, :, :3], axis=-1) < reach
    rows, cols = np.nonzero(near)
    hit = np.zeros(len(moved), bool)
    if len(rows):
        ok = iou_3d_paired(moved[rows], targets[cols]) >= matching.inlier_iou
        hit[rows[ok]] = True
    return int(hit.sum())


def refine_on_tracks(query: FrameObservations, pose: Pose4, verified, tracks: list, matching: MatchingConfig,
                     keyframes: dict, poses: dict) -> Pose4:
    """Refit a relocalized pose on the map's object tracks: each query detection matched (as
    a verified inlier) to an observation of a track is paired with the track's centre — the
    median of all its observations lifted into the map, so much less noisy than one
    keyframe's detection — and the 4-DoF pose is refitted on those centres, weighted by range
    like the relative-pose refit. Centres come from the boxes relative poses use
    (``FrameObservations.boxes``: fitted ones where the detector also gives full boxes); the
    refit is kept only when the query's full boxes still verify against the tracks' boxes.
    ``verified``: (keyframe id, relative pose, T_query_map) of the agreeing keyframes."""
    owner = {}
    for t in tracks:
        for kf, det in t.observations:
            owner[(int(kf), int(det))] = t
    votes = {}
    for k, rel, _ in verified:
        for iq, ik in rel.inliers:
            t = owner.get((k, int(ik)))
            if t is not None:
                votes.setdefault(int(iq), []).append(t.track_id)
    by_id = {t.track_id: t for t in tracks}
    pairs = [(iq, by_id[max(set(ids), key=ids.count)]) for iq, ids in votes.items()]
    if len(pairs) < 3:
        return pose
    idx = [iq for iq, _ in pairs]
    q = query.boxes[idx]

    def centre(track):
        lifted = [poses[int(k)].inverse().transform_points(keyframes[int(k)].boxes[int(d), :3][None])[0]
                  for k, d in track.observations if int(k) in poses and int(k) in keyframes]
        return np.median(lifted, axis=0)

    target = np.array([centre(t) for _, t in pairs])
    rng = np.linalg.norm(q[:, :3], axis=1)
    w = 1.0 / (matching.refine_sigma_m + matching.refine_sigma_per_m * rng) ** 2
    t_map_q = kabsch_4dof(q[:, :3], target, w)
    moved = t_map_q.transform_boxes(query.map_boxes[idx])
    reps = np.array([t.box for _, t in pairs])
    if np.mean(iou_3d_paired(moved, reps) >= matching.inlier_iou) < matching.min_inlier_ratio:
        return pose
    return t_map_q.inverse()
