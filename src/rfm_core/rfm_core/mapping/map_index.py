"""What relocalization looks up in a map, indexed once per map revision (a map of a
building holds thousands of objects; a query must cost what its own neighbourhood costs).

- keyframe retrieval: the registered keyframes' bag-of-objects descriptors stacked in one
  matrix (one product per query);
- the map's object boxes (every track's box and its views lifted into the map) in a k-d
  tree over their centres: a query placed in the map is compared with the boxes within
  reach only;
- each keyframe detection's track, and each track's centre (the median of its views);
- per query detection, the tracks most like it (embedding and size), for matching a view
  against the map's objects without trying every object of the map;
- the map's depth points: the registered keyframes' clouds lifted into the map and merged on
  a voxel grid (:class:`MapCloud`), what a view is aligned to when its detections alone do not
  place it (a view sees surfaces several keyframes saw, rarely all of them one keyframe's).

The tracks are built only when first needed (keyframe retrieval does not need them). No ROS
here.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from rfm_core.geometry import iou_3d_paired, wrap_angle
from rfm_core.matching.classical import size_similarity
from rfm_core.clouds import PointIndex, voxel_means
from rfm_core.matching.view_graph import bag_of_objects

__all__ = ['MapIndex', 'MapCloud', 'track_boxes']

CLOUD_VOXEL_M = 0.05            #: the map's depth points: one per cell of this grid
CLOUD_MAX_POINTS = 300_000      #: a map with more is cut into tiles: ...
CLOUD_TILE_M = 4.0              #: ... squares this wide, each the points of the keyframes whose camera is
CLOUD_REACH_M = 8.0             #: ... within this of the square (what a camera in it sees)
CLOUD_CACHE = 4                 #: tiles kept (the latest built)
FLOOR_KEYFRAMES = 7             #: registered keyframes whose floors make the map's floor under a camera


class MapCloud:
    """Depth points in the map frame, ready to be aligned to (the ``source`` of
    :func:`rfm_core.matching.relative_pose.track_on_points`): ``cloud`` and its
    :meth:`point_index`."""

    def __init__(self, clouds: list, voxel_m: float = CLOUD_VOXEL_M):
        self.cloud = voxel_means(np.concatenate(clouds) if clouds else np.zeros((0, 3)), voxel_m).astype(np.float32)
        self._index = None

    def point_index(self):
        if self._index is None:
            self._index = PointIndex(self.cloud)
        return self._index


def track_boxes(tracks: list) -> np.ndarray:
    """(M, 7) the map's object boxes a query is checked against: every track's box and its
    views lifted into the map."""
    if not tracks:
        return np.zeros((0, 7))
    return np.concatenate([t.boxes for t in tracks] + [np.array([t.box for t in tracks])])


class MapIndex:
    """One revision of a map, indexed for relocalization. ``keyframes``: id ->
    FrameObservations; ``poses``: id -> T_k_map of the registered ones; ``descriptors``: id ->
    bag of objects; ``tracks``: the map's object tracks, or a callable giving them (built on
    first use)."""

    def __init__(self, keyframes: dict, poses: dict, descriptors: dict, tracks):
        self.keyframes = keyframes
        self.poses = poses
        self._descriptors = descriptors
        self._tracks_source = tracks
        self._tracks = None if callable(tracks) else list(tracks)
        self._retrieval = None
        self._targets = None
        self._owner = None
        self._centres: dict = {}
        self._observers = None
        self._embeddings = None
        self._cameras = None                    # every registered keyframe's camera (_camera_table)
        self._clouds: dict = {}                 # tile (None: the whole map) -> MapCloud
        self._cloud_table = None
        self._floor_table = None                # the registered keyframes' floors (_floors)

    # ------------------------------------------------------------------ keyframes

    def candidates(self, query, count: int) -> list:
        """Registered keyframes with two or more detections most similar to ``query`` by bag
        of objects (the latest ones when descriptors are missing or of another size)."""
        if self._retrieval is None:
            ids = [k for k in self.poses if self._descriptors.get(k) is not None and len(self.keyframes[k]) >= 2]
            sizes = {self._descriptors[k].size for k in ids}
            matrix = np.stack([self._descriptors[k] for k in ids]) if len(sizes) == 1 else None
            self._retrieval = (ids, matrix)
        ids, matrix = self._retrieval
        desc = bag_of_objects(query)
        if matrix is None or not np.any(desc) or matrix.shape[1] != desc.size:
            return ids[-count:]
        sims = matrix @ desc
        top = np.argpartition(-sims, count - 1)[:count] if len(ids) > count else np.arange(len(ids))
        return [ids[i] for i in top[np.lexsort((top, -sims[top]))]]

    def keyframes_near(self, centre, yaw: float, reach_m: float, count: int) -> list:
        """Registered keyframes with two or more detections near a camera at ``centre``
        looking along ``yaw``: nearest first by centre distance plus yaw difference (a metre
        per radian), those within ``reach_m`` plus a quarter turn, at most ``count``."""
        ids, centres, yaws, detected, _ = self._camera_table()
        sel = np.flatnonzero(detected)
        far = np.linalg.norm(centres[sel] - np.asarray(centre, float), axis=1) + np.abs(wrap_angle(yaws[sel] - yaw))
        order = np.argsort(far, kind='stable')[:count]
        return [ids[sel[i]] for i in order if far[i] <= reach_m + np.pi / 2]

    def _camera_table(self):
        """(ids, camera centres, yaws, has two or more detections, has depth points) of every
        registered keyframe, in the map's order; built once per map revision."""
        if self._cameras is None:
            ids = list(self.poses)
            inv = [self.poses[k].inverse() for k in ids]
            self._cameras = (ids, np.array([t.t for t in inv]).reshape(-1, 3), np.array([t.yaw for t in inv]),
                             np.array([len(self.keyframes[k]) >= 2 for k in ids], bool),
                             np.array([len(self.keyframes[k].cloud) > 0 for k in ids], bool))
        return self._cameras

    def keyframes_with_points_near(self, centre, count: int) -> list:
        """Ids of the registered keyframes with depth points, nearest ``centre`` first (at most
        ``count``)."""
        ids, centres, _, _, points = self._camera_table()
        with_points = np.flatnonzero(points)
        order = np.argsort(np.linalg.norm(centres[with_points] - centre, axis=1))[:count]
        return [ids[with_points[i]] for i in order]

    def cloud_near(self, centre) -> MapCloud:
        """The map's depth points around a camera at ``centre``: all of them, for a map of at
        most :data:`CLOUD_MAX_POINTS` points (built once per map revision); else those of the
        :data:`CLOUD_TILE_M` square holding ``centre`` (the keyframes whose camera is within
        :data:`CLOUD_REACH_M` of it; built when first needed, the latest :data:`CLOUD_CACHE` kept)."""
        if self._cloud_table is None:                      # (keyframe ids with points, their camera centres, points)
            ids, centres, _, _, points = self._camera_table()
            chosen = np.flatnonzero(points)
            self._cloud_table = ([ids[i] for i in chosen], centres[points],
                                 sum(len(self.keyframes[ids[i]].cloud) for i in chosen))
        ids, centres, points = self._cloud_table
        if points <= CLOUD_MAX_POINTS:
            key, chosen = None, range(len(ids))
        else:
            key = tuple(np.floor(np.asarray(centre, float)[:2] / CLOUD_TILE_M).astype(int))
            middle = (np.array(key) + 0.5) * CLOUD_TILE_M
            reach = CLOUD_REACH_M + CLOUD_TILE_M / np.sqrt(2)
            chosen = np.flatnonzero(np.linalg.norm(centres[:, :2] - middle, axis=1) <= reach)
        if key not in self._clouds:
            if len(self._clouds) >= CLOUD_CACHE:
                self._clouds.pop(next(iter(self._clouds)))
            # lifted into the map when a tile is built: what is kept is at most CLOUD_CACHE tiles' points
            self._clouds[key] = MapCloud([self.poses[ids[i]].inverse().transform_points(
                np.asarray(self.keyframes[ids[i]].cloud, float)).astype(np.float32) for i in chosen])
        return self._clouds[key]

    def _floors(self):
        """(k-d tree over the centres of the registered keyframes that measured the floor, the
        floor's height in the map under each); None with fewer than :data:`FLOOR_KEYFRAMES`."""
        if self._floor_table is None:
            ids, centres = self._camera_table()[:2]
            floors = centres[:, 2] - np.array([self.keyframes[i].camera_height for i in ids], float)
            known = np.isfinite(floors)
            self._floor_table = ((cKDTree(centres[known]), floors[known]) if known.sum() >= FLOOR_KEYFRAMES
                                 else False)
        return self._floor_table or None

    def floor_under(self, centre) -> float:
        """The floor's height in the map under a camera at ``centre``: the median over the
        :data:`FLOOR_KEYFRAMES` registered keyframes nearest it of their camera's height in
        the map less their measured height above the floor (NaN: too few measured one). One
        keyframe's floor plane is sometimes another surface (a bed, a seat); the map's floor
        is what most keyframes around agree on."""
        table = self._floors()
        if table is None:
            return float('nan')
        tree, floors = table
        return float(np.median(floors[tree.query(np.asarray(centre, float), k=FLOOR_KEYFRAMES)[1]]))

    def nearest_keyframe(self, centre) -> int | None:
        """The registered keyframe whose camera is nearest ``centre``."""
        if not self.poses:
            return None
        ids, centres = self._camera_table()[:2]
        return ids[int(np.argmin(np.linalg.norm(centres - np.asarray(centre, float), axis=1)))]

    # ------------------------------------------------------------------ objects

    @property
    def tracks(self) -> list:
        if self._tracks is None:
            self._tracks = list(self._tracks_source())
        return self._tracks

    @property
    def boxes(self) -> np.ndarray:
        """(T, 7) the tracks' boxes."""
        return self._objects()[0]

    def _objects(self):
        if self._targets is None:
            tracks = self.tracks
            boxes = np.array([t.box for t in tracks], float).reshape(-1, 7)
            targets = track_boxes(tracks)
            tree = cKDTree(targets[:, :3]) if len(targets) else None
            half = 0.5 * float(np.linalg.norm(targets[:, 3:6], axis=1).max()) if len(targets) else 0.0
            self._targets = (boxes, targets, tree, half)
        return self._targets

    @property
    def targets(self) -> np.ndarray:
        """(M, 7) :func:`track_boxes` of the map."""
        return self._objects()[1]

    def near(self, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (rows into ``boxes``, rows into :attr:`targets`) whose centres are within
        half the sum of the two boxes' diagonals: the only pairs that can overlap."""
        _, targets, tree, half = self._objects()
        boxes = np.asarray(boxes, float).reshape(-1, 7)
        if tree is None or not len(boxes):
            return np.zeros(0, int), np.zeros(0, int)
        own = 0.5 * np.linalg.norm(boxes[:, 3:6], axis=1)
        lists = tree.query_ball_point(boxes[:, :3], own + half)
        rows = np.repeat(np.arange(len(boxes)), [len(c) for c in lists])
        cols = np.fromiter((c for cs in lists for c in cs), int, len(rows))
        if not len(rows):
            return rows, cols
        reach = own[rows] + 0.5 * np.linalg.norm(targets[cols, 3:6], axis=1)
        keep = np.linalg.norm(boxes[rows, :3] - targets[cols, :3], axis=1) < reach
        return rows[keep], cols[keep]

    def best_iou(self, boxes: np.ndarray) -> np.ndarray:
        """(N,) each of ``boxes``' (in the map) largest IoU with one of the map's boxes (0:
        none within reach)."""
        rows, cols = self.near(boxes)
        best = np.zeros(len(boxes))
        if len(rows):
            np.maximum.at(best, rows, iou_3d_paired(np.asarray(boxes, float)[rows], self.targets[cols]))
        return best

    def overlapping(self, boxes: np.ndarray, iou: float) -> np.ndarray:
        """(N,) whether each of ``boxes`` (in the map) overlaps one of the map's boxes by ``iou``."""
        return self.best_iou(boxes) >= iou

    def track_of(self, keyframe_id: int, detection: int):
        """The track a keyframe's detection belongs to (None: in none)."""
        if self._owner is None:
            self._owner = {(int(k), int(d)): t for t in self.tracks for k, d in t.observations}
        return self._owner.get((int(keyframe_id), int(detection)))

    def centre(self, track) -> np.ndarray:
        """A track's centre: the median of the centres of its views in registered keyframes,
        each lifted into the map by its keyframe's pose (from the boxes relative poses use)."""
        if track.track_id not in self._centres:
            lifted = [self.poses[int(k)].inverse().transform_points(self.keyframes[int(k)].boxes[int(d), :3][None])[0]
                      for k, d in track.observations if int(k) in self.poses and int(k) in self.keyframes]
            self._centres[track.track_id] = np.median(lifted, axis=0)
        return self._centres[track.track_id]

    def observers(self, m: int) -> list:
        """[(keyframe, detection)] of registered keyframes that saw track ``m`` (an index into
        :attr:`tracks`)."""
        if self._observers is None:
            self._observers = [[(int(k), int(d)) for k, d in t.observations
                                if int(k) in self.poses and int(k) in self.keyframes] for t in self.tracks]
        return self._observers[m]

    def similar(self, boxes: np.ndarray, embeddings: np.ndarray, gate: float, count: int):
        """Candidate correspondences of a view with the map's objects: for each view box,
        the ``count`` tracks of compatible size (``size_similarity`` >= ``gate``) most like
        it: by embedding where the view's and the tracks' agree in size, then by size.
        Returns (view rows, track rows), each view's best first."""
        tb = self.boxes
        boxes = np.asarray(boxes, float).reshape(-1, 7)
        if not len(tb) or not len(boxes):
            return np.zeros(0, int), np.zeros(0, int)
        sizes = size_similarity(boxes, tb)                                    # (N, T)
        score = sizes.copy()
        dim = embeddings.shape[1] if embeddings is not None and embeddings.ndim == 2 else 0
        track_emb = self._track_embeddings()
        if dim and track_emb is not None and track_emb.shape[1] == dim:
            emb = embeddings.astype(np.float64)
            emb = emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-9)
            score = score + emb @ track_emb.T
        score = np.where(sizes >= gate, score, -np.inf)
        rows, cols = [], []
        for n in range(len(boxes)):
            ok = np.flatnonzero(np.isfinite(score[n]))
            best = ok[np.argsort(-score[n, ok], kind='stable')[:count]]
            rows.append(np.full(len(best), n))
            cols.append(best)
        return np.concatenate(rows), np.concatenate(cols)

    def _track_embeddings(self) -> np.ndarray | None:
        """(T, D) the tracks' embeddings (None when their sizes differ)."""
        if self._embeddings is None:
            sizes = {t.embedding.size for t in self.tracks}
            self._embeddings = (np.stack([t.embedding for t in self.tracks]).astype(np.float64)
                                if len(sizes) == 1 else False)
        return self._embeddings if self._embeddings is not False else None
