"""Object tracks: union-find over inlier object matches, lifted boxes, representatives,
merging and suppression (paper 3.5 and appendix "Track merging").

An observation is one detection (keyframe id, detection index). Tracks are the connected
components of the inlier object matches of the edges that survived averaging, restricted
to registered keyframes; each observation's box is lifted into the map frame with its
keyframe's pose. The representative box is the observation with the highest geometric mean
of its average 3D IoU with the track's other observations and its detection score; the
label is the maximum of the score-weighted class distribution.

Duplicates (one object, two tracks without an inlier path between them) are merged when
their track affinity — the mean over observation pairs of a matching score times
(GIoU3D + 1) / 2 — exceeds ``merge_affinity``, considering only pairs whose representatives'
GIoU3D exceeds ``merge_giou_gate``; a track that is not merged but overlaps a stronger one
with IoU3D above ``suppress_iou`` is suppressed. The paper's matching score comes from the
learned matcher, which is near zero for different objects. Here it is the appearance
similarity (cosine + 1) / 2 of the two tracks when the two observations overlap as a
verified match would (IoU3D >= 0.25), else zero: that needs no extra matcher runs and
keeps weak embeddings (colour statistics) from merging neighbouring objects.

Not in the paper: a track enters the map only when its views make it likely to be a real
object (:func:`view_evidence`): a fragment of furniture, a piece of wall or a burst of
sensor noise that one keyframe detected and the many others looking at the same place did
not is left out.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from rfm_core.geometry import box_corners, giou_3d_paired, gravity_aligned_rotation, iou_3d_paired
from rfm_core.settings import constant, setting

__all__ = ['TrackConfig', 'Track', 'build_tracks', 'view_evidence']


@dataclass(frozen=True)
class TrackConfig:
    merge_giou_gate: float = setting(-0.6, 'Merging: ignore track pairs with GIoU3D below this', lo=-1.0, hi=1.0,
                                     paper=-0.6)
    merge_affinity: float = setting(0.25, 'Merge duplicate tracks whose affinity exceeds this', lo=0.0, hi=2.0,
                                    paper=0.25)
    suppress_iou: float = setting(0.15, 'Suppress an unmerged track overlapping a stronger one above this IoU3D',
                                  lo=0.0, hi=1.0, paper=0.15)
    min_observations: int = setting(1, 'Publish tracks seen in at least this many keyframes', lo=1, hi=1000)
    single_view_iou: float = constant(0.25, 'Mutual-IoU term of a track seen once (the least a verified second view '
                                      'would show)', lo=0.0, hi=1.0)
    max_pair_observations: int = constant(6, 'Merging: observations per track compared (best scores)',
                                          lo=1, hi=1000)
    detection_rate: float = constant(0.5, "View evidence: chance that a real object in a keyframe's view is "
                                     'detected and matched into its track', lo=0.01, hi=0.99)
    recurrence_rate: float = constant(0.05, 'View evidence: chance that a phantom (a fragment, structure, noise) '
                                      'recurs at the same place in another view', lo=0.001, hi=0.99)
    min_evidence: float = setting(0.5, "Publish tracks whose probability of being a real object (from their views) "
                                  'is at least this (0: every track)', lo=0.0, hi=1.0)


@dataclass
class Track:
    track_id: int                        #: stable: from the track's earliest observation
    box: np.ndarray                      #: (7,) representative box in the map frame
    score: float                         #: geometric mean of ``quality`` and ``evidence``
    label: str
    class_distribution: dict
    observations: np.ndarray             #: (M, 2) keyframe id, detection index
    boxes: np.ndarray                    #: (M, 7) lifted observation boxes (map frame)
    scores: np.ndarray                   #: (M,) detection scores
    embedding: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  #: mean, unit
    quality: float = 0.0                 #: the paper's track score: mutual IoU x detection score, geometric mean
    evidence: float = 1.0                #: probability of being a real object (:func:`view_evidence`)
    expected_views: int = 0              #: registered keyframes that saw it or should have

    @property
    def num_observations(self) -> int:
        return len(self.observations)


def _representative(boxes, scores, single_view_iou):
    m = len(boxes)
    if m == 1:
        mutual = np.array([single_view_iou])
    else:                                 # mean IoU with the others; each pair once
        ii, jj = np.triu_indices(m, 1)
        iou = iou_3d_paired(boxes[ii], boxes[jj])
        mutual = (np.bincount(ii, iou, m) + np.bincount(jj, iou, m)) / (m - 1)
    quality = np.sqrt(np.clip(mutual, 0, 1) * np.clip(scores, 0, 1))
    best = int(np.argmax(quality))       # ties: the first view (the oldest keyframe)
    return best, float(quality[best])


def _make_track(obs, boxes, scores, labels, embeds, cfg) -> Track:
    order = np.lexsort((obs[:, 1], obs[:, 0]))
    obs, boxes, scores = obs[order], boxes[order], scores[order]
    labels = [labels[i] for i in order]
    embeds = embeds[order] if len(embeds) else embeds
    best, quality = _representative(boxes, scores, cfg.single_view_iou)
    dist = {}
    for lab, s in zip(labels, scores):
        if lab:
            dist[lab] = dist.get(lab, 0.0) + float(s)
    total = sum(dist.values())
    dist = {k: v / total for k, v in dist.items()} if total > 0 else {}
    label = max(dist, key=dist.get) if dist else ''
    emb = embeds.mean(0) if len(embeds) and embeds.shape[1] else np.zeros(0, np.float32)
    if emb.size:
        emb = emb / max(np.linalg.norm(emb), 1e-9)
    return Track(int(obs[0, 0]) * 4096 + int(obs[0, 1]), boxes[best].copy(), quality, label, dist,
                 obs, boxes, scores, emb.astype(np.float32), quality=quality)


def build_tracks(keyframes: dict, poses: dict, matches, config: TrackConfig | None = None,
                 carried: dict | None = None) -> list:
    """Tracks of the registered keyframes.

    ``keyframes``: {keyframe id: FrameObservations}; ``poses``: {keyframe id: Pose4 T_k_map}
    (registered keyframes only); ``matches``: iterable of (keyframe a, index a, keyframe b,
    index b) inlier object matches of the surviving edges; ``carried``: {(keyframe, index):
    views} of culled keyframes whose detection of the same object that detection stands for
    (:func:`view_evidence`).
    """
    cfg = config or TrackConfig()
    kf_ids = [k for k in keyframes if k in poses and len(keyframes[k])]
    if not kf_ids:
        return []
    offset, start = {}, 0
    for k in kf_ids:
        offset[k] = start
        start += len(keyframes[k])
    n = start
    obs = np.zeros((n, 2), np.int64)
    boxes = np.zeros((n, 7))
    scores = np.zeros(n)
    labels = [''] * n
    dims = {keyframes[k].embeddings.shape[1] for k in kf_ids}
    dim = dims.pop() if len(dims) == 1 else 0
    embeds = np.zeros((n, dim), np.float32)
    for k in kf_ids:
        f = keyframes[k]
        sl = slice(offset[k], offset[k] + len(f))
        obs[sl, 0], obs[sl, 1] = k, np.arange(len(f))
        boxes[sl] = poses[k].inverse().transform_boxes(f.map_boxes)
        scores[sl] = f.scores
        labels[sl] = list(f.labels) if len(f.labels) == len(f) else [''] * len(f)
        if dim:
            embeds[sl] = f.embeddings
    rows, cols = [], []
    for ka, ia, kb, ib in matches:
        if ka in offset and kb in offset and ia < len(keyframes[ka]) and ib < len(keyframes[kb]):
            rows.append(offset[ka] + ia)
            cols.append(offset[kb] + ib)
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    order = np.argsort(comp, kind='stable')
    groups = np.split(order, np.flatnonzero(np.diff(comp[order])) + 1)
    tracks = [_make_track(obs[g], boxes[g], scores[g], [labels[i] for i in g], embeds[g] if dim else embeds[:0], cfg)
              for g in groups if len(g)]
    tracks = _merge_and_suppress(tracks, cfg)
    view_evidence(tracks, keyframes, poses, cfg, carried)
    tracks = [t for t in tracks if t.num_observations >= cfg.min_observations and t.evidence >= cfg.min_evidence]
    tracks.sort(key=lambda t: t.track_id)
    return tracks


def view_evidence(tracks: list, keyframes: dict, poses: dict, config: TrackConfig | None = None,
                  carried: dict | None = None) -> None:
    """Set each track's ``evidence``: the probability that it is a real object, from the
    keyframes that saw it and those that should have.

    A registered keyframe should see a track when the track's centre projects into its image
    (10% margin) within the map's viewing reach (the 90th percentile of its detections'
    distances: no detector range needed). A real object in view is detected and matched into
    its track with probability ``detection_rate``; a phantom (a fragment of furniture, a piece
    of wall, sensor noise) recurs at the same place with probability ``recurrence_rate``. With
    the best detection score as the prior, a track detected in k of the E keyframes that
    should see it has log-odds

        logit(score) + (k - 1) log(p_real / p_phantom) + (E - k) log((1 - p_real) / (1 - p_phantom)).

    So a box seen once from a place that twenty keyframes looked at is a phantom, and one seen
    once from the only view there is keeps its score. The track's ``score`` becomes the
    geometric mean of its quality and this evidence. A keyframe culled from the map
    (``carried``: {(keyframe, index): views} of the detections that stand for culled
    keyframes' detections of the same object) still counts as a view that saw the object."""
    cfg = config or TrackConfig()
    ids = [k for k in poses if k in keyframes and len(keyframes[k])]
    if not tracks or not ids:
        return
    reach = float(np.percentile(np.concatenate([np.linalg.norm(keyframes[k].boxes[:, :3], axis=1) for k in ids]),
                                90))
    centres = np.array([t.box[:3] for t in tracks])
    row = {k: i for i, k in enumerate(ids)}
    should = np.zeros((len(ids), len(tracks)), bool)
    for i, k in enumerate(ids):
        f = keyframes[k]
        if f.intrinsics is None:                                  # field of view unknown: no evidence
            continue
        aligned = poses[k].transform_points(centres)              # the keyframe's gravity-aligned frame
        cam = aligned @ gravity_aligned_rotation(f.gravity_cam)   # optical frame: R^T p
        z = np.maximum(cam[:, 2], 1e-9)
        k_ = f.intrinsics
        u, v = k_.fx * cam[:, 0] / z + k_.cx, k_.fy * cam[:, 1] / z + k_.cy
        mu, mv = 0.1 * k_.width, 0.1 * k_.height
        should[i] = ((cam[:, 2] > 0.1) & (u >= mu) & (u < k_.width - mu) & (v >= mv) & (v < k_.height - mv)
                     & (np.linalg.norm(aligned, axis=1) <= reach))
    p, q = cfg.detection_rate, cfg.recurrence_rate
    hit, miss = np.log(p / q), np.log((1 - p) / (1 - q))
    for j, t in enumerate(tracks):
        seen = np.unique(t.observations[:, 0])
        rows = [row[k] for k in seen if k in row]
        extra = sum(carried.get((int(k), int(d)), 0) for k, d in t.observations) if carried else 0
        expected = np.count_nonzero(should[:, j]) + np.count_nonzero(~should[rows, j]) + extra
        prior = float(np.clip(np.max(t.scores), 0.01, 0.99))
        logit = np.log(prior / (1 - prior)) + (len(seen) + extra - 1) * hit + (expected - len(seen) - extra) * miss
        t.evidence = float(1.0 / (1.0 + np.exp(-np.clip(logit, -50, 50))))
        t.expected_views = int(expected)
        t.score = float(np.sqrt(t.quality * t.evidence))


def _candidate_pairs(tracks: list, cfg: TrackConfig):
    """Track pairs worth comparing: representatives' GIoU3D above the gate (paper) and
    overlapping observation extents (observations that never overlap cannot be the same)."""
    reps = np.array([t.box for t in tracks])
    lo = np.array([box_corners(t.boxes).reshape(-1, 3).min(0) for t in tracks])
    hi = np.array([box_corners(t.boxes).reshape(-1, 3).max(0) for t in tracks])
    overlap = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=-1)
    ii, jj = np.nonzero(np.triu(overlap, k=1))
    if len(ii) == 0:
        return ii, jj, np.zeros(0)
    keep = giou_3d_paired(reps[ii], reps[jj]) > cfg.merge_giou_gate
    ii, jj = ii[keep], jj[keep]
    return ii, jj, iou_3d_paired(reps[ii], reps[jj])


def _affinities(tracks: list, ii, jj, cfg: TrackConfig) -> np.ndarray:
    """Track affinity of each candidate pair: the mean over observation pairs of
    (matching score) x (GIoU3D + 1) / 2, the matching score being the appearance similarity
    (cosine + 1) / 2 of the tracks when the two observations overlap as an inlier match
    would (IoU3D >= 0.25), else 0. Observations: the ``max_pair_observations`` best scored."""
    if len(ii) == 0:
        return np.zeros(0)
    best = [np.argsort(-t.scores, kind='stable')[:cfg.max_pair_observations] for t in tracks]
    a_idx, b_idx, pair = [], [], []
    for p, (i, j) in enumerate(zip(ii, jj)):
        na, nb = len(best[i]), len(best[j])
        a_idx.append(np.repeat(best[i], nb))
        b_idx.append(np.tile(best[j], na))
        pair.append(np.full(na * nb, p))
    pair = np.concatenate(pair)
    a_boxes = np.concatenate([tracks[i].boxes[a] for i, a in zip(ii, a_idx)])
    b_boxes = np.concatenate([tracks[j].boxes[b] for j, b in zip(jj, b_idx)])
    overlaps = iou_3d_paired(a_boxes, b_boxes) >= 0.25
    g = np.zeros(len(overlaps))           # only overlapping pairs count: GIoU of those alone
    g[overlaps] = (giou_3d_paired(a_boxes[overlaps], b_boxes[overlaps]) + 1.0) / 2.0
    sim = np.ones(len(ii))
    for p, (i, j) in enumerate(zip(ii, jj)):
        ea, eb = tracks[i].embedding, tracks[j].embedding
        if ea.size and ea.size == eb.size:
            sim[p] = (float(ea @ eb) + 1.0) / 2.0
    per_obs = np.where(overlaps, sim[pair], 0.0) * g
    return np.bincount(pair, weights=per_obs, minlength=len(ii)) / np.bincount(pair, minlength=len(ii))


def _merge_and_suppress(tracks: list, cfg: TrackConfig) -> list:
    if len(tracks) < 2:
        return tracks
    ii, jj, iou = _candidate_pairs(tracks, cfg)
    affinity = _affinities(tracks, ii, jj, cfg)
    parent = list(range(len(tracks)))

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    overlapping = []
    for i, j, a, o in zip(ii, jj, affinity, iou):
        if a > cfg.merge_affinity:
            ri, rj = find(i), find(j)
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
        elif o > cfg.suppress_iou:
            overlapping.append((i, j))
    groups = {}
    for i in range(len(tracks)):
        groups.setdefault(find(i), []).append(i)
    merged, index = [], {}
    for root, members in groups.items():
        if len(members) == 1:
            t = tracks[members[0]]
        else:
            parts = [tracks[m] for m in members]
            labels = []
            for p in parts:
                labels += [p.label] * p.num_observations
            dim = {p.embedding.size for p in parts}
            emb = (np.concatenate([np.repeat(p.embedding[None], p.num_observations, 0) for p in parts])
                   if len(dim) == 1 and dim.pop() else np.zeros((0, 0), np.float32))
            t = _make_track(np.concatenate([p.observations for p in parts]),
                            np.concatenate([p.boxes for p in parts]),
                            np.concatenate([p.scores for p in parts]), labels, emb, cfg)
        for m in members:
            index[m] = len(merged)
        merged.append(t)
    # suppression: of two overlapping unmerged tracks keep the stronger (score, then size)
    dropped = set()
    for i, j in overlapping:
        a, b = index[i], index[j]
        if a == b or a in dropped or b in dropped:
            continue
        ta, tb = merged[a], merged[b]
        weaker = b if (ta.score, ta.num_observations) >= (tb.score, tb.num_observations) else a
        dropped.add(weaker)
    return [t for k, t in enumerate(merged) if k not in dropped]
