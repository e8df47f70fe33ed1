"""Relative pose from matched boxes, with geometric verification (paper section 3.4).

For every minimal set of two matched objects, the corners of both boxes give 16 point
correspondences and a 4-DoF Kabsch alignment (yaw + translation, gravity known). Each
object match is then an inlier when the transferred box overlaps its match with
IoU3D >= ``inlier_iou``. A sample is accepted when its own two matches are inliers and at
least ``min_inlier_ratio`` of all matches are; the accepted sample with the lowest mean
matching error (1 - IoU3D over all matches) wins. Corners of inlier matches that land within
``corner_inlier_m`` of their counterparts are kept for bundle adjustment. Beyond the paper,
the winning pose is refitted on all its inlier matches, weighted by their distance from the
camera (its yaw from the boxes' orientations), and kept when it still verifies and explains
the matches as well.

For a detector that judges distance from RGB alone (``range_error`` > 0), whose
errors run along the viewing rays, two things change: before its IoU is measured, a
transferred box may slide along the viewing ray by the distance error the detector is
expected to make, and the refit is the maximum-likelihood pose under that anisotropic error
over every match consistent with the sample's pose.

The yaw symmetry of boxes (a quarter turn with swapped sizes is the same box) is resolved
geometrically: the first object of a sample proposes every quarter turn consistent with its
sizes, and the second object takes the quarter turn closest to the proposed yaw.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace
from itertools import combinations

import numpy as np

from rfm_core.geometry import (
    Pose4, align_4dof_anisotropic, box_corners, iou_3d_paired, kabsch_4dof, kabsch_4dof_batch, ray_covariances,
    wrap_angle, yaw_matrix,
)
from rfm_core.matching.classical import ObjectMatches, size_similarity
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.corners import closest_turn, corner_permutation, quarter_turn_table
from rfm_core.matching.points import align_points

__all__ = ['RelativePose', 'YawPrior', 'estimate_relative_pose', 'estimate_on_full_boxes', 'estimate_by_consensus',
           'pair_hypotheses', 'box_hits', 'with_points',
           'with_camera_heights', 'with_walls', 'with_surfaces', 'track_on_points']

#: two poses of :func:`estimate_by_consensus` are distinct when their translations differ by more (m) ...
CONSENSUS_DISTINCT_M = 0.25
#: ... or their yaws (deg)
CONSENSUS_DISTINCT_DEG = 5.0


@dataclass
class RelativePose:
    """A verified relative pose: ``pose`` is T_b_a (maps frame a's gravity-aligned camera
    frame into frame b's: p_b = Rz(yaw) p_a + t)."""

    pose: Pose4
    inliers: np.ndarray          #: (K, 2) detection indices (a, b) of inlier matches
    inlier_ious: np.ndarray      #: (K,) IoU3D after transfer
    inlier_scores: np.ndarray    #: (K,) matcher scores
    mean_error: float            #: mean 1 - IoU3D over all matches of the winning sample
    num_matches: int
    corner_inliers: list = field(default_factory=list)  #: (ia, corner_a, ib, corner_b, error_m)
    on_points: bool = False      #: the two frames' depth points fixed every direction of ``pose`` (:func:`with_points`)

    @property
    def inlier_ratio(self) -> float:
        return len(self.inliers) / max(self.num_matches, 1)

    def swap_index_order(self) -> 'RelativePose':
        """Inliers and corner inliers as (b, a) index pairs, in place; the pose stays T_b_a
        (``estimate_relative_pose(boxes_of_target, boxes_of_source)`` read as the source's
        pose of the target with (source, target) pairs). Returns self."""
        self.inliers = self.inliers[:, ::-1].copy()
        self.corner_inliers = [(ib, cb, ia, ca, e) for ia, ca, ib, cb, e in self.corner_inliers]
        return self


def _best_turn(candidates, yaw):
    """The quarter turn whose implied relative yaw is closest to ``yaw``."""
    if not candidates:
        return None
    return min(candidates, key=lambda kc: abs(wrap_angle(kc[1] - yaw)))


@dataclass(frozen=True)
class YawPrior:
    """The relative yaw measured otherwise (the gyroscope): hypotheses further than
    ``tolerance_rad`` from ``yaw_rad`` are not considered, and each single match proposes
    the translation under that yaw (verified like any sample: by two objects at least). The
    winner's own yaw is kept (boxes fix it within the tolerance; taking the measured yaw
    and refitting the translation on box centres alone was measured worse)."""

    yaw_rad: float
    tolerance_rad: float


def estimate_relative_pose(boxes_a: np.ndarray, boxes_b: np.ndarray, matches: ObjectMatches,
                           config: MatchingConfig | None = None, yaw_prior: YawPrior | None = None) -> RelativePose | None:
    """Verified T_b_a from matched boxes of two frames (gravity-aligned camera frames), or
    None when no minimal sample passes verification. ``yaw_prior``: T_b_a's yaw as measured
    by other means (see :class:`YawPrior`)."""
    cfg = config or MatchingConfig()
    n = len(matches)
    if n < max(cfg.min_matches, 2):
        return None
    a = np.asarray(boxes_a, dtype=np.float64)[matches.a]
    b = np.asarray(boxes_b, dtype=np.float64)[matches.b]
    turns = quarter_turn_table(a, b, cfg.size_consistency)
    corners_a = box_corners(a)                                   # (n, 8, 3)
    corners_b = box_corners(b)
    # Every minimal sample and yaw hypothesis, solved and verified in one batch.
    hyps = []
    for i, j in combinations(range(n), 2):
        for k_i, yaw in turns[i]:
            pick = _best_turn(turns[j], yaw)
            if pick is not None:
                hyps.append((i, j, k_i, pick[0]))
    best = None
    if hyps or yaw_prior is not None:
        h = np.array(hyps, dtype=int).reshape(-1, 4)
        if len(h):
            perms = np.stack([corner_permutation(k) for k in range(4)])          # (4, 8)
            src = np.concatenate([corners_a[h[:, 0]], corners_a[h[:, 1]]], axis=1)  # (H, 16, 3)
            dst = np.concatenate([np.take_along_axis(corners_b[h[:, 0]], perms[h[:, 2]][..., None], 1),
                                  np.take_along_axis(corners_b[h[:, 1]], perms[h[:, 3]][..., None], 1)],
                                 axis=1)
            yaws, trans = kabsch_4dof_batch(src, dst)
        else:
            yaws, trans = np.zeros(0), np.zeros((0, 3))
        if yaw_prior is not None:
            # hypotheses the measured yaw rules out are dropped; each single match proposes
            # the translation under the measured yaw (its own match as the sample's pair)
            keep = np.abs(wrap_angle(yaws - yaw_prior.yaw_rad)) <= yaw_prior.tolerance_rad
            single = np.arange(n)
            h = np.concatenate([h[keep], np.stack([single, single, np.zeros(n, int), np.zeros(n, int)], 1)])
            rot = yaw_matrix(yaw_prior.yaw_rad)
            yaws = np.concatenate([yaws[keep], np.full(n, yaw_prior.yaw_rad)])
            trans = np.concatenate([trans[keep], b[:, :3] - a[:, :3] @ rot.T])
        moved = np.repeat(a[None], len(h), axis=0)                            # (H, n, 7)
        moved[..., :3] = np.einsum('hij,hnj->hni', yaw_matrix(yaws), a[None, :, :3]) + trans[:, None]
        moved[..., 6] = wrap_angle(a[None, :, 6] + yaws[:, None])
        ious = _overlap(moved.reshape(-1, 7), np.tile(b, (len(h), 1)), cfg).reshape(len(h), n)
        inlier = ious >= cfg.inlier_iou
        rows = np.arange(len(h))
        ok = (inlier[rows, h[:, 0]] & inlier[rows, h[:, 1]] & (inlier.mean(1) >= cfg.min_inlier_ratio)
              & (inlier.sum(1) >= 2))                   # two objects, whatever proposed the pose
        if np.any(ok):
            errors = np.where(ok, np.mean(1.0 - ious, axis=1), np.inf)
            w = int(np.argmin(errors))               # the lowest mean error (first on ties)
            best = (float(errors[w]), Pose4(yaws[w], trans[w]), ious[w], inlier[w])
    if best is None:
        return None
    error, pose, ious, inlier = best
    pose, ious, error = _refine(pose, a, b, corners_a, corners_b, turns, inlier, ious, error, cfg)
    inlier = ious >= cfg.inlier_iou
    idx = np.flatnonzero(inlier)
    return RelativePose(
        pose=pose,
        inliers=np.stack([matches.a[idx], matches.b[idx]], axis=1),
        inlier_ious=ious[idx], inlier_scores=np.asarray(matches.scores)[idx],
        mean_error=error, num_matches=n,
        corner_inliers=_corner_inliers(pose, a, b, matches, idx, cfg))


def estimate_on_full_boxes(obs_a, obs_b, matcher, config: MatchingConfig | None = None) -> RelativePose | None:
    """T_b_a as :func:`estimate_relative_pose` of ``obs_a``'s and ``obs_b``'s boxes gives it, but
    matched (``matcher``) and verified on the objects' full boxes (the detector's completion),
    and kept only where the fitted boxes' directions agree with its yaw, turned to them
    (:func:`_turned_to_surfaces`); None where either frame has no full boxes. Seen from far
    apart, the fitted boxes (the visible part of each object, which repeats from frame to
    frame of a stream) are different parts of one object and verify half the pairs of photos
    the full boxes verify; the full boxes' yaw is the looser, and the poses they get wrong are
    mostly turned by 5-45 deg, which the visible surfaces' directions contradict
    (docs/design-notes.md)."""
    cfg = config or MatchingConfig()
    if cfg.full_box_yaw_tolerance_deg <= 0 or not (has_full_boxes(obs_a) and has_full_boxes(obs_b)):
        return None
    full_a, full_b = copy.copy(obs_a), copy.copy(obs_b)
    full_a.boxes, full_b.boxes = np.asarray(obs_a.full_boxes, np.float64), np.asarray(obs_b.full_boxes, np.float64)
    rel = estimate_relative_pose(full_a.boxes, full_b.boxes, matcher.match(full_a, full_b), cfg)
    if rel is None:
        return None
    rel.corner_inliers = []                                  # (corners of the full boxes, not of ``boxes``)
    return _turned_to_surfaces(rel, obs_a, obs_b, cfg)


def estimate_by_consensus(obs_a, obs_b, config: MatchingConfig | None = None) -> RelativePose | None:
    """T_b_a of two separate views matched on the geometry of their full boxes alone: each
    pair of boxes of compatible size proposes a pose (T_b_a's yaw from the two boxes' yaws up
    to quarter turns, the translation from their centres); the pose that lands the most of
    a's boxes on b's (:func:`box_hits`), three at least and more than any distinct pose, gives
    the matches, verified as :func:`estimate_relative_pose` verifies them and then checked and
    turned by the fitted boxes as :func:`estimate_on_full_boxes` is. None where either frame
    has no full boxes or fewer than three. Where a learned matcher, trained on pairs of one
    walk, matches too few objects of two views far apart, the boxes' layout still does: on
    tuning photo pairs (docs/design-notes.md)."""
    cfg = config or MatchingConfig()
    if not (has_full_boxes(obs_a) and has_full_boxes(obs_b)) or min(len(obs_a), len(obs_b)) < 3:
        return None
    a, b = np.asarray(obs_a.full_boxes, np.float64), np.asarray(obs_b.full_boxes, np.float64)
    compatible = size_similarity(a, b) >= cfg.size_ratio_gate
    ii, jj = np.nonzero(compatible)
    if not len(ii):
        return None
    yaws, trans = pair_hypotheses(a, b, ii, jj)
    hits = box_hits(a, b, compatible, yaws, trans)                                 # (H, N, M)
    count = hits.any(2).sum(1)
    order = np.argsort(-count, kind='stable')
    best = int(order[0])
    pose = Pose4(float(yaws[best]), trans[best])
    distinct = [count[h] for h in order[1:] if count[h] >= 3
                and not (Pose4(float(yaws[h]), trans[h]).inverse() @ pose).within(CONSENSUS_DISTINCT_M,
                                                                                  CONSENSUS_DISTINCT_DEG)]
    if count[best] < 3 or (distinct and max(distinct) >= count[best]):
        return None
    moved = pose.transform_points(a[:, :3])
    pairs = {}
    for n in np.flatnonzero(hits[best].any(1)):
        cols = np.flatnonzero(hits[best, n])
        m = int(cols[np.argmin(np.linalg.norm(moved[n, :2] - b[cols, :2], axis=1))])
        pairs.setdefault(m, int(n))                           # one to one
    matches = ObjectMatches(np.array(list(pairs.values()), int), np.array(list(pairs), int), np.ones(len(pairs)))
    rel = estimate_relative_pose(a, b, matches, cfg)
    if rel is None:
        return None
    rel.corner_inliers = []                                  # (corners of the full boxes, not of ``boxes``)
    return _turned_to_surfaces(rel, obs_a, obs_b, cfg)


def pair_hypotheses(a: np.ndarray, b: np.ndarray, ii: np.ndarray, jj: np.ndarray, yaws=None) -> tuple:
    """Poses T_b_a (yaws (H,), translations (H, 3)) that put box ``a[ii[k]]`` on box ``b[jj[k]]``:
    each pair's yaw from the two boxes' yaws up to quarter turns (4 per pair), or ``yaws`` (K, Y)
    given per pair (a gyroscope's), and the translation from their centres."""
    if yaws is None:                              # box yaws are known up to quarter turns
        yaws = (b[jj, 6] - a[ii, 6])[:, None] + 0.5 * np.pi * np.arange(4)[None]
    hi, hj, hy = np.repeat(ii, yaws.shape[1]), np.repeat(jj, yaws.shape[1]), yaws.reshape(-1)
    return hy, b[hj, :3] - np.einsum('hab,hb->ha', yaw_matrix(hy), a[hi, :3])


def box_hits(query_boxes: np.ndarray, track_boxes_: np.ndarray, compatible: np.ndarray, yaws: np.ndarray,
             trans: np.ndarray) -> np.ndarray:
    """(H, N, M) whether box n lands on box m of the other frame (a map's track) under pose
    hypothesis h (T_other_this: yaw, translation): horizontal centres within a quarter of the
    two footprints' diagonals, heights within a quarter of the two heights, and sizes
    ``compatible`` (N, M)."""
    moved = np.einsum('hab,nb->hna', yaw_matrix(yaws), query_boxes[:, :3]) + trans[:, None]
    reach = 0.25 * (np.linalg.norm(query_boxes[:, None, 3:5], axis=-1)
                    + np.linalg.norm(track_boxes_[None, :, 3:5], axis=-1))
    up = 0.25 * (query_boxes[:, None, 5] + track_boxes_[None, :, 5])
    d = np.linalg.norm(moved[:, :, None, :2] - track_boxes_[None, None, :, :2], axis=-1)
    dz = np.abs(moved[:, :, None, 2] - track_boxes_[None, None, :, 2])
    return (d < reach[None]) & (dz < up[None]) & compatible[None]


def has_full_boxes(obs) -> bool:
    """Whether the detector gave ``obs``'s full boxes apart from its fitted ones."""
    return obs.full_boxes is not None and len(obs.full_boxes) == len(obs.boxes)


def _turned_to_surfaces(rel: RelativePose, obs_a, obs_b, config: MatchingConfig) -> RelativePose | None:
    """``rel`` (T_b_a from the full boxes, (a, b) index pairs) checked and turned by the fitted
    boxes (``boxes``: the visible surfaces' directions, precise where their extents are
    different parts of each object): None unless at least two verified objects turn their
    fitted boxes by ``rel``'s yaw within ``full_box_yaw_tolerance_deg`` (up to a quarter turn,
    a box's symmetry); else ``rel`` turned by those objects' mean disagreement about the
    centroid of its verified full boxes in frame a, which keep their place (in place; returns
    ``rel``)."""
    inl = np.asarray(rel.inliers, int).reshape(-1, 2)
    turn = (np.asarray(obs_b.boxes, np.float64)[inl[:, 1], 6] - np.asarray(obs_a.boxes, np.float64)[inl[:, 0], 6]
            - rel.pose.yaw)
    turn = (turn + np.pi / 4) % (np.pi / 2) - np.pi / 4             # from the nearest quarter turn
    agree = np.abs(turn) <= np.radians(config.full_box_yaw_tolerance_deg)
    if np.sum(agree) < 2:
        return None
    yaw, correction = float(rel.pose.yaw), float(np.mean(turn[agree]))
    pivot = np.asarray(obs_a.full_boxes, np.float64)[inl[:, 0], :3].mean(0)
    t = np.asarray(rel.pose.t, np.float64) + (yaw_matrix(yaw) - yaw_matrix(yaw + correction)) @ pivot
    rel.pose = Pose4(float(wrap_angle(yaw + correction)), t)
    return rel


def with_camera_heights(rel: RelativePose | None, source, target,
                        config: MatchingConfig | None = None) -> RelativePose | None:
    """``rel`` (T_source_target) with its vertical translation replaced by the difference of
    the two frames' camera heights above the floor (``FrameObservations.camera_height``)
    where both measured one and it is within ``height_tolerance_m`` of the boxes' (in
    place; returns ``rel``). In 4-DoF the height decouples from yaw and horizontal
    translation, so the boxes' fit of those stays optimal. The floor plane fixes a camera's
    height to about a centimetre; box centres, partial and snapped to different supports from
    view to view, to several (the vertical part of a depth detector's edge errors). A larger
    disagreement means one frame took another surface (a table top) for the floor: the boxes
    then decide."""
    cfg = config or MatchingConfig()
    if rel is None or cfg.height_tolerance_m <= 0:
        return rel
    hs, ht = float(source.camera_height), float(target.camera_height)
    if not (np.isfinite(hs) and np.isfinite(ht)):
        return rel
    t = np.array(rel.pose.t, dtype=np.float64)
    if abs(t[2] - (ht - hs)) <= cfg.height_tolerance_m:
        t[2] = ht - hs
        rel.pose = Pose4(rel.pose.yaw, t)
    return rel


def with_walls(rel: RelativePose | None, source, target, config: MatchingConfig | None = None) -> RelativePose | None:
    """``rel`` (T_source_target) corrected by the walls both frames measured
    (``FrameObservations.walls``; in place, returns ``rel``). A wall of the target, turned
    by the pose's yaw, pairs with the source's wall whose normal is within
    ``wall_tolerance_deg`` of it and whose plane the pose puts within ``wall_tolerance_m`` of
    it. A plane fitted to a wall's many points gives its direction to a tenth of a degree
    and the camera's distance to it to a centimetre or two; boxes the image border cuts, or
    partly hidden, move their centres by several centimetres and their faces by a degree.

    1. Yaw: the pairs' normals turn the yaw by their mean disagreement, weighed
       (``wall_yaw_sigma_deg`` each) against the pose's (``box_yaw_sigma_deg``); the pose
       turns about the centroid of its matched target boxes, which keep their place.
    2. Translation: each pair fixes it along its normal (n . t = d_source - d_target, error
       ``wall_sigma_m``), weighed against the pose's (``box_translation_sigma_m`` per axis).
       Two walls at an angle fix the horizontal translation; one fixes it across the wall.
    The height is kept."""
    cfg = config or MatchingConfig()
    if rel is None or cfg.wall_tolerance_m <= 0:
        return rel
    ws, wt = np.asarray(source.walls, float).reshape(-1, 3), np.asarray(target.walls, float).reshape(-1, 3)
    if not len(ws) or not len(wt):
        return rel
    pairs = _wall_pairs(rel.pose, ws, wt, cfg)
    if not pairs:
        return rel
    yaw, t = float(rel.pose.yaw), np.array(rel.pose.t, dtype=np.float64)
    # 1. yaw, turning the pose about the matched target boxes (the camera for a motion edge)
    rot = yaw_matrix(yaw)[:2, :2]
    heading_s, heading_t = np.arctan2(ws[:, 1], ws[:, 0]), np.arctan2(wt[:, 1], wt[:, 0])
    turns = [wrap_angle(heading_s[j] - heading_t[i] - yaw) for i, j in pairs]    # R(turn) R n_t = n_s
    w_box, w_wall = 1.0 / np.radians(cfg.box_yaw_sigma_deg) ** 2, 1.0 / np.radians(cfg.wall_yaw_sigma_deg) ** 2
    turn = w_wall * float(np.sum(turns)) / (w_box + w_wall * len(turns))
    inl = np.asarray(rel.inliers, int).reshape(-1, 2)
    pivot = (np.asarray(target.boxes, float)[inl[:, 1], :2].mean(0) if len(inl) and len(target.boxes)
             else np.zeros(2))
    turned = yaw_matrix(yaw + turn)[:2, :2]
    t[:2] += (rot - turned) @ pivot
    yaw += turn
    # 2. translation along the walls' normals
    info = np.eye(2) / cfg.box_translation_sigma_m ** 2
    rhs = info @ t[:2]
    for i, j in pairs:
        n = ws[j, :2]
        info = info + np.outer(n, n) / cfg.wall_sigma_m ** 2
        rhs = rhs + n * (ws[j, 2] - wt[i, 2]) / cfg.wall_sigma_m ** 2
    t[:2] = np.linalg.solve(info, rhs)
    rel.pose = Pose4(float(wrap_angle(yaw)), t)
    return rel


def with_points(rel: RelativePose | None, source, target, config: MatchingConfig | None = None,
                predicted: Pose4 | None = None) -> RelativePose | None:
    """``rel`` (T_source_target) refined on the two frames' depth points
    (``FrameObservations.cloud``; :func:`rfm_core.matching.points.align_points`, in place;
    returns ``rel``): kept where at least ``point_min_overlap`` of the target's points lie
    on the source's surfaces and the correction is within ``point_max_correction_m`` /
    ``point_max_correction_deg`` (not compared with the starting pose's overlap: a fit closer
    to the truth often holds fewer points within ``point_match_m``, as in
    :func:`track_on_points`). ``predicted`` (a
    stream's motion prediction of T_source_target): where it differs from the boxes' pose
    by more than ``point_match_m`` or 1 deg, the points are aligned from it as well, and the
    alignment that puts more points on the source's surfaces is kept (two boxes cut by the
    image border can place a frame decimetres off; the prediction from the frame before
    does not drift that far). ``rel.on_points``: the points fixed every direction."""
    cfg = config or MatchingConfig()
    if rel is None or not len(source.cloud) or not len(target.cloud):
        return rel
    starts = [rel.pose]
    if predicted is not None and (np.linalg.norm(np.asarray(predicted.t) - rel.pose.t) > cfg.point_match_m
                                  or np.degrees(abs(predicted.angle_to(rel.pose))) > 1.0):
        starts.append(predicted)
    best = None
    for start in starts:
        found = align_points(start, target.cloud, source.point_index(), cfg.point_search_m, cfg.point_match_m)
        if (found is None or found.overlap < cfg.point_min_overlap
                or np.linalg.norm(np.asarray(found.pose.t) - rel.pose.t) > cfg.point_max_correction_m
                or np.degrees(abs(found.pose.angle_to(rel.pose))) > cfg.point_max_correction_deg):
            continue
        if best is None or found.overlap > best.overlap:
            best = found
    if best is not None:
        rel.pose = best.pose
        rel.on_points = best.free == 0
    return rel


def track_on_points(predicted: Pose4, source, target, config: MatchingConfig | None = None):
    """``target``'s frame placed in ``source``'s on the depth points alone, from ``predicted``
    (T_source_target, a stream's motion prediction):
    aligned both in 4-DoF and in 6-DoF (the frames' gravity may differ by a degree or two;
    where the points pin the tilt poorly, its fit can slide instead), the alignment that puts
    more points on the source's surfaces kept of those with at least ``point_track_min_overlap``
    of the target's points on them (and of those, the one that leaves fewer directions free, if
    either does: a 6-DoF fit can leave a direction free that the 4-DoF one fixes), returned as
    a :class:`~rfm_core.matching.points.PointAlignment`; None if neither. The caller checks the
    directions left free and the motion. (The refined overlap is not compared with the
    prediction's: a fit that holds a few points fewer than its start is as close to the truth
    as one that holds more.)

    The overlaps are shares of what the source's surfaces can hold: divided by the share of
    the source's own points that lie on a surface (a cloud aligned to itself scores exactly
    that). Noisy depth (an active-stereo camera at a few metres) leaves half its points off
    any surface the normals trust, against a fifth for clean depth, so a raw share would ask
    noisier frames to overlap more."""
    cfg = config or MatchingConfig()
    if not len(source.cloud) or not len(target.cloud):
        return None
    index = source.point_index()
    surface = max(float(index.usable.mean()), 1e-3)
    found = None
    for tilt in (True, False):
        a = align_points(predicted, target.cloud, index, cfg.point_search_m, cfg.point_match_m, tilt=tilt)
        if a is None:
            continue
        a = replace(a, overlap=min(a.overlap / surface, 1.0), overlap_before=min(a.overlap_before / surface, 1.0))
        if a.overlap >= cfg.point_track_min_overlap and (
                found is None or (-a.free, a.overlap) > (-found.free, found.overlap)):
            found = a
    return found


def with_surfaces(rel: RelativePose | None, source, target, config: MatchingConfig | None = None,
                  points: bool = True, predicted: Pose4 | None = None) -> RelativePose | None:
    """``rel`` (T_source_target) corrected by the surfaces the two frames measured besides
    their boxes: the floor (:func:`with_camera_heights`), the walls (:func:`with_walls`), then
    (``points``) every depth point (:func:`with_points`, also from ``predicted``; in place,
    returns ``rel``)."""
    rel = with_walls(with_camera_heights(rel, source, target, config), source, target, config)
    return with_points(rel, source, target, config, predicted) if points else rel


def _wall_pairs(pose: Pose4, ws: np.ndarray, wt: np.ndarray, cfg: MatchingConfig) -> list:
    """(target wall, source wall) index pairs: each target wall, turned by ``pose``'s yaw,
    with the nearest source wall (one-to-one) whose normal and plane it agrees with."""
    normals = wt[:, :2] @ yaw_matrix(pose.yaw)[:2, :2].T              # target's normals turned: R n
    gap = ws[None, :, 2] - wt[:, None, 2] - (ws[:, :2] @ np.asarray(pose.t, float)[:2])[None, :]   # d_s - d_t - n_s . t
    near = (normals @ ws[:, :2].T > np.cos(np.radians(cfg.wall_tolerance_deg))) & (np.abs(gap) <= cfg.wall_tolerance_m)
    pairs, used = [], set()
    for i in range(len(wt)):
        for j in np.flatnonzero(near[i])[np.argsort(np.abs(gap[i, near[i]]))]:
            if j not in used:
                used.add(int(j))
                pairs.append((i, int(j)))
                break
    return pairs


def _refine(pose, a, b, corners_a, corners_b, turns, inlier, ious, error, cfg):
    """Local optimisation (not in the paper): refit the pose on all inlier matches, each
    weighted by the inverse variance of a detection at its distance (sigma = refine_sigma_m
    + refine_sigma_per_m x range): box centres when there are three or more inliers, else the
    corners (each with the quarter turn that agrees with the sample's yaw); the yaw then comes
    from the boxes' orientations (:func:`_face_yaw`: partial boxes' centres shift towards the
    camera that saw them, by a different amount per object, and their spread turns the pose).
    Kept when it still verifies and its mean box error grows by at most
    ``refine_max_error_increase`` (partial boxes of a depth-only detector have biased
    centres; the IoU criterion notices). Under along-ray errors that refit only starts
    :func:`_refit_along_rays`, which is kept whenever it verifies."""
    src, dst, weights, used = [], [], [], []
    for m in np.flatnonzero(inlier):
        pick = _best_turn(turns[m], pose.yaw)
        if pick is not None:
            used.append(m)
            src.append(corners_a[m])
            dst.append(corners_b[m][corner_permutation(pick[0])])
            rng = 0.5 * (np.linalg.norm(a[m, :3]) + np.linalg.norm(b[m, :3]))
            weights.append(1.0 / (cfg.refine_sigma_m + cfg.refine_sigma_per_m * rng) ** 2)
    if len(src) < 2:
        return pose, ious, error
    src, dst, weights = np.array(src), np.array(dst), np.array(weights)
    if len(src) >= 3:
        cs, cd = src.mean(1), dst.mean(1)
        refit = kabsch_4dof(cs, cd, weights)
        for _ in range(3):                  # robust: a wrong inlier (a look-alike) loses its say
            r = np.linalg.norm(refit.transform_points(cs) - cd, axis=1)
            refit = kabsch_4dof(cs, cd, weights / (1.0 + (r / 0.05) ** 2))
    else:
        refit = kabsch_4dof(src.reshape(-1, 3), dst.reshape(-1, 3), np.repeat(weights, 8))
    if cfg.along_rays:
        refit = _refit_along_rays(refit, a[:, :3], b[:, :3], cfg)
    else:
        refit = _face_yaw(refit, a[used], b[used], weights)
    refit_ious = _overlap(refit.transform_boxes(a), b, cfg)
    if np.mean(refit_ious >= cfg.inlier_iou) < cfg.min_inlier_ratio:
        return pose, ious, error
    if (not cfg.along_rays and cfg.refine_max_error_increase >= 0
            and np.mean(1.0 - refit_ious) > error + cfg.refine_max_error_increase):
        return pose, ious, error
    return refit, refit_ious, float(np.mean(1.0 - refit_ious))


def _face_yaw(pose: Pose4, a, b, weights, scale_deg: float = 3.0) -> Pose4:
    """``pose`` with its yaw from the matched boxes' orientations (each pair's yaw
    difference taken modulo a quarter turn about ``pose``'s yaw, Cauchy-weighted at
    ``scale_deg``) and its translation refitted on the box centres under that yaw."""
    d = wrap_angle(b[:, 6] - a[:, 6] - pose.yaw)
    d = (d + np.pi / 4) % (np.pi / 2) - np.pi / 4             # a quarter turn is the same box
    delta = 0.0
    for _ in range(5):
        w = weights / (1.0 + ((d - delta) / np.radians(scale_deg)) ** 2)
        delta = float(np.sum(w * d) / np.sum(w))
    yaw = float(wrap_angle(pose.yaw + delta))
    t = np.sum(w[:, None] * (b[:, :3] - a[:, :3] @ yaw_matrix(yaw).T), axis=0) / np.sum(w)
    return Pose4(yaw, t)


def _overlap(moved, b, cfg) -> np.ndarray:
    """IoU3D of transferred boxes with their matches (paired). Under along-ray errors
    (``range_error``) each transferred box may first slide along frame b's viewing ray,
    scaled about the camera by up to one standard deviation of the two frames' combined
    distance error (as far as it brings the box centres together): a correct match whose
    distance was misjudged by a few percent then still verifies, a box elsewhere does not."""
    if not cfg.along_rays:
        return iou_3d_paired(moved, b)
    cm, cb = moved[:, :3], b[:, :3]
    tolerance = np.sqrt(2.0) * (cfg.range_error + cfg.range_error_per_m * np.linalg.norm(cb, axis=1))
    scale = np.einsum('ni,ni->n', cm, cb) / np.maximum(np.einsum('ni,ni->n', cm, cm), 1e-9)
    scaled = moved.copy()
    scaled[:, :6] *= np.clip(scale, 1.0 - tolerance, 1.0 + tolerance)[:, None]
    return iou_3d_paired(scaled, b)


def _refit_along_rays(pose: Pose4, ca, cb, cfg) -> Pose4:
    """Maximum-likelihood refit on the box centres of every match consistent with ``pose``
    under the along-ray error model (``range_error``): a monocular detector's
    misjudged distance can cost a true match its IoU inlier status, yet its bearing still
    says much; a wrong match loses its say through a Cauchy weight."""
    def cov(points):
        rng = np.linalg.norm(points, axis=1)
        return ray_covariances(points, cfg.refine_sigma_m + cfg.refine_sigma_per_m * rng,
                               cfg.range_error + cfg.range_error_per_m * rng)

    cov_a, cov_b = cov(ca), cov(cb)
    rot = pose.rotation
    r = pose.transform_points(ca) - cb
    keep = np.einsum('ni,nij,nj->n', r, np.linalg.inv(rot @ cov_a @ rot.T + cov_b), r) < 16.0  # 4 sigma
    if keep.sum() < 2:
        return pose
    ca, cb, cov_a, cov_b = ca[keep], cb[keep], cov_a[keep], cov_b[keep]
    robust = np.ones(len(ca))
    for _ in range(3):
        pose, chi2 = align_4dof_anisotropic(ca, cb, cov_a, cov_b, pose.yaw, weights=robust)
        robust = 1.0 / (1.0 + chi2 / 9.0)          # Cauchy at 3 sigma
    return pose


def _corner_inliers(pose: Pose4, a, b, matches, idx, cfg) -> list:
    """Corner correspondences of inlier matches within ``corner_inlier_m`` after transfer."""
    out = []
    moved = pose.transform_boxes(a[idx])
    for m, box in zip(idx, moved):
        # the quarter turn of box b that best matches the transferred box's yaw
        k = closest_turn(b[m], box[6])
        perm = corner_permutation(k)
        ca = box_corners(box)
        cb = box_corners(b[m])[perm]
        err = np.linalg.norm(ca - cb, axis=1)
        for c in np.flatnonzero(err < cfg.corner_inlier_m):
            out.append((int(matches.a[m]), int(c), int(matches.b[m]), int(perm[c]), float(err[c])))
    return out
