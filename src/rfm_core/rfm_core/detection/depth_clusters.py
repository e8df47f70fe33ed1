"""`depth_clusters`: 3D boxes from RGB-D: geometric clusters, boxes refined by a small learned model.

1. Back-project the depth image (every ``stride``-th pixel) into the gravity-aligned camera
   frame; estimate normals from neighbouring pixels.
2. Remove room structure: the floor (lowest large upward-facing surface), the ceiling, and
   walls — large vertical planes with (almost) nothing visible behind them, found by
   RANSAC on the bird's-eye view.
3. Cluster the remaining points by connectivity on a voxel grid; split clusters at support
   surfaces (an upward-facing surface with points above it: small objects on tables).
4. Fit a gravity-aligned box to each cluster: yaw from the minimum-area footprint, extents
   from robust percentiles, completed amodally — down to the floor or support it stands
   on (from any height when something nearer hides its bottom), and back to the wall
   behind it (or to its visible width) when its far side cannot be seen.
5. Score: by default a learned box refiner (:mod:`rfm_core.detection.box_refiner`, a small
   PointNet trained on simulated rooms) reads each cluster's points and predicts its
   objectness (the score), the object's full box and a class; fragments, clutter and
   pieces of structure score low and are dropped, overlapping boxes are suppressed, and the
   fitted boxes are published for relative poses (they repeat from view to view) with the
   predicted ones attached as each detection's full box for the map. With
   ``box_refiner=''`` (training the refiner) the fitted boxes are kept, scored by support
   (points) and shape and calibrated by a small logistic model
   (:mod:`rfm_core.detection.score_model`).
   Each box is described by an embedding of its colours (hue/value histograms, mean
   colour), sorted size and height above the floor.

Works on any registered RGB-D stream with gravity; it never reads instance ids.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from rfm_core.detection.base import Detector, DetectorConfig, DetectorInput, finalize
from rfm_core.detection.score_model import DEFAULT_SCORE_MODEL, box_features, load_score_model
from rfm_core.geometry import gravity_aligned_rotation
from rfm_core.observations import FrameObservations
from rfm_core.settings import constant, setting

__all__ = ['DepthClustersConfig', 'DepthClustersDetector', 'Candidate', 'Candidates', 'EMBEDDING_DIM']

EMBEDDING_DIM = 24


@dataclass(frozen=True)
class DepthClustersConfig(DetectorConfig):
    stride: int = setting(2, 'Input resolution: use every n-th pixel', lo=1, hi=8)
    min_depth_m: float = setting(0.2, 'Ignore depth nearer than this (m)', lo=0.0, hi=10.0)
    max_depth_m: float = setting(6.0, 'Ignore depth farther than this (m)', lo=0.1, hi=100.0)
    surface_tolerance_m: float = constant(0.04, 'Floor / ceiling / wall inlier distance at 0 m (m) ...',
                                          lo=0.001, hi=1.0)
    depth_noise_per_m2: float = constant(0.002, '... plus this x range^2 (depth error growth, 1/m)', lo=0.0, hi=1.0)
    wall_min_height_m: float = constant(1.0, 'A wall spans at least this much vertically (m)', lo=0.1, hi=10.0)
    wall_max_behind: float = constant(0.03, 'Share of points allowed behind a wall', lo=0.0, hi=1.0)
    max_walls: int = constant(4, 'Walls removed per frame', lo=0, hi=20)
    ransac_iterations: int = constant(120, 'RANSAC iterations per plane', lo=1, hi=10000)
    voxel_m: float = constant(0.04, 'Clustering connectivity (m)', lo=0.005, hi=1.0)
    min_cluster_points: int = constant(25, 'Least points of a cluster (after striding)', lo=1, hi=100000)
    support_min_points: int = constant(20, 'Upward-facing points that make a support surface', lo=1, hi=100000)
    floor_snap_m: float = constant(0.3, 'Extend boxes down to the floor within this (m), or from any height when '
                                   'an occluder hides the bottom', lo=0.0, hi=5.0)
    occluder_gap_m: float = constant(0.1, 'An occluder is this much nearer than the object (m)', lo=0.0, hi=5.0)
    wall_snap_m: float = constant(0.5, "Extend a box's unseen back to a wall within this (m)", lo=0.0, hi=5.0)
    amodal_min_depth_m: float = constant(0.3, 'A box whose back is unseen gets the depth of its visible width '
                                         '(footprints are rarely slabs), clipped to at least this (m) ...',
                                         lo=0.0, hi=5.0)
    amodal_max_depth_m: float = constant(0.7, '... and at most this (m)', lo=0.0, hi=5.0)
    truncated_score_factor: float = constant(0.6, 'Score multiplier of boxes cut by the image border',
                                             lo=0.0, hi=1.0)
    score_model: str = setting('default', "Calibrated score of the heuristic boxes: 'default' (shipped), a JSON "
                               "file from rfm train-depth-score, or '' for the raw score", read_only=True)
    box_refiner: str = setting('default', "Learned box refiner: 'default' (shipped weights), a checkpoint from rfm "
                               "train-box-refiner, or '' for the heuristic boxes scored by score_model",
                               read_only=True)
    nms_iou: float = constant(0.3, 'Box refiner: of published boxes overlapping more than this (3D IoU), keep '
                              'the best scored', lo=0.0, hi=1.0)
    max_gravity_correction_deg: float = constant(6.0, 'Align gravity with the floor plane when visible and within '
                                                 'this of the input gravity (deg)',
                                                 lo=0.0, hi=90.0)
    seed: int = constant(0, 'RANSAC sampling seed', lo=0, hi=2**31 - 1)


def _normals(points: np.ndarray, step: int = 1) -> np.ndarray:
    """Unit normals (h, w, 3) of an organised point image, NaN where undefined.

    Central differences over ``step`` samples each side: a wider baseline keeps quantised
    depth (steps of centimetres at a few metres) from tilting normals of grazing surfaces.
    """
    dx = np.full_like(points, np.nan)
    dy = np.full_like(points, np.nan)
    dx[:, step:-step] = points[:, 2 * step:] - points[:, :-2 * step]
    dy[step:-step, :] = points[2 * step:, :] - points[:-2 * step, :]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid='ignore', divide='ignore'):
        n = n / norm
    # orient towards the camera (origin)
    flip = np.sum(n * points, axis=-1) > 0
    n[flip] *= -1
    return n


def _peak_height(z: np.ndarray, lowest: bool, min_count: int, bin_m: float = 0.02):
    """Height of the lowest (or highest) histogram peak of z with at least min_count points."""
    if len(z) < min_count:
        return None
    lo, hi = np.min(z), np.max(z)
    bins = max(int(np.ceil((hi - lo) / bin_m)), 1)
    counts, edges = np.histogram(z, bins=bins, range=(lo, lo + bins * bin_m))
    smooth = counts + np.r_[0, counts[:-1]] + np.r_[counts[1:], 0]
    hits = np.flatnonzero(smooth >= min_count)
    if not len(hits):
        return None
    # from the first significant bin, climb to the top of its peak (noise tails come first)
    j, step = (hits[0], 1) if lowest else (hits[-1], -1)
    while 0 <= j + step < len(smooth) and smooth[j + step] > smooth[j]:
        j += step
    sel = (z >= edges[max(j - 1, 0)]) & (z < edges[min(j + 2, len(edges) - 1)])
    return float(np.median(z[sel]))


def _in_footprint(xy: np.ndarray, surface_xy: np.ndarray, margin: float) -> np.ndarray:
    """Whether points lie inside the convex hull of a surface's points, grown by margin."""
    from scipy.spatial import ConvexHull, QhullError  # noqa: PLC0415

    if len(surface_xy) > 400:                 # the hull needs no more points
        surface_xy = surface_xy[np.linspace(0, len(surface_xy) - 1, 400).astype(int)]
    try:
        hull = ConvexHull(surface_xy)
    except (QhullError, ValueError):          # degenerate (collinear) surface
        return np.zeros(len(xy), dtype=bool)
    # hull.equations rows: (nx, ny, d) with n.p + d <= 0 inside, n unit length
    eq = hull.equations
    return np.all(xy @ eq[:, :2].T + eq[:, 2] <= margin, axis=1)



def percentiles(a: np.ndarray, qs) -> list:
    """np.percentile(a, qs, axis=0) (linear interpolation, the same values) from one
    partial sort: several times faster on the small arrays of box fitting."""
    a = np.asarray(a)
    n = a.shape[0]
    pos = [q / 100.0 * (n - 1) for q in qs]
    lows = [int(np.floor(x)) for x in pos]
    kth = sorted({k for lo in lows for k in (lo, min(lo + 1, n - 1))})
    part = np.partition(a, kth, axis=0)
    out = []
    for x, lo in zip(pos, lows):
        frac = x - lo
        below, above = part[lo], part[min(lo + 1, n - 1)]
        out.append(below + frac * (above - below) if frac else below.copy())
    return out

@dataclass
class Candidate:
    """One cluster of object points and the box fitted to it (gravity-aligned camera frame)."""

    points: np.ndarray            #: (n, 3) m
    normals: np.ndarray           #: (n, 3) unit, towards the camera
    pixels: np.ndarray            #: (n, 2) full-resolution (row, column)
    colours: np.ndarray | None    #: (n, 3) uint8, None without a colour image
    box: np.ndarray               #: (7,) the fitted, amodally completed box
    raw_score: float              #: points x shape (before the truncation factor)
    truncated: bool               #: cut by the image border
    on_support: bool              #: stands on a support surface (a table top), not the floor
    bottom_hidden: bool           #: its bottom is hidden by an occluder or the border
    box_2d: list                  #: [x0, y0, x1, y1] pixels


@dataclass
class Candidates:
    frame: DetectorInput          #: the input with the floor-refined gravity
    floor_z: float | None         #: floor height in the gravity-aligned frame, when seen
    ceiling_z: float | None
    items: list                   #: [Candidate]
    walls: list = field(default_factory=list)   #: [(unit normal (2,), distance)] in that frame


class DepthClustersDetector(Detector):
    name = 'depth_clusters'
    needs_depth = True

    def __init__(self, config: DepthClustersConfig | None = None):
        self.config = config or DepthClustersConfig()
        path = self.config.score_model
        self.score_model = (load_score_model(DEFAULT_SCORE_MODEL if path == 'default' else path)
                            if path else None)
        self.box_refiner = None
        if self.config.box_refiner:
            from rfm_core.detection.box_refiner import BoxRefiner  # noqa: PLC0415  (torch)
            self.box_refiner = BoxRefiner.load(self.config.box_refiner, nms_iou=self.config.nms_iou)

    # ------------------------------------------------------------------ pipeline

    def detect(self, frame: DetectorInput) -> FrameObservations:
        cfg = self.config
        found = self.candidates(frame)
        frame, items = found.frame, found.items
        boxes = np.array([c.box for c in items]).reshape(-1, 7)          # fitted
        full = None
        if self.box_refiner is not None:
            refined, scores, labels = self.box_refiner.refine(found)
            keep = self.box_refiner.suppress(boxes, scores)
            items = [items[i] for i in keep]
            boxes, scores, labels = boxes[keep], scores[keep], [labels[i] for i in keep]
            full = refined[keep]
        else:
            # boxes cut by the image border are completed from a partial view: less certain
            raw = np.array([c.raw_score * (cfg.truncated_score_factor if c.truncated else 1.0)
                            for c in items])
            labels = [''] * len(items)
            scores = raw
            if self.score_model is not None and len(items):
                # the raw score decides which boxes are kept (score_threshold), the calibrated
                # one how they rank
                intr = frame.intrinsics
                calibrated = self.score_model(box_features(raw, boxes, [c.box_2d for c in items],
                                                           intr.fx, intr.fy))
                scores = np.where(raw >= cfg.score_threshold, np.maximum(calibrated, cfg.score_threshold), 0.0)
        embeds = [self._embedding(c.colours, box, found.floor_z) for c, box in zip(items, boxes)]
        return finalize(frame, boxes, scores, labels, np.array(embeds).reshape(len(items), EMBEDDING_DIM),
                        [c.box_2d for c in items], cfg, self.name, full_boxes=full,
                        camera_height=-found.floor_z if found.floor_z is not None else float('nan'),
                        walls=[(n[0], n[1], d) for n, d in found.walls if d > 0.05])

    def candidates(self, frame: DetectorInput) -> 'Candidates':
        """Steps 1-4: one :class:`Candidate` per cluster with its fitted box and raw score,
        in the gravity-aligned frame of the (floor-refined) gravity of ``Candidates.frame``."""
        cfg = self.config
        frame.validate(needs_depth=True)
        intr = frame.intrinsics
        s = max(int(cfg.stride), 1)
        depth = frame.depth[::s, ::s].astype(np.float32)
        h, w = depth.shape
        v, u = np.mgrid[0:h, 0:w]
        u, v = u * s, v * s
        valid = np.isfinite(depth) & (depth > cfg.min_depth_m) & (depth < cfg.max_depth_m)
        z = np.where(valid, depth, np.nan)
        cam = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], -1)
        gravity = np.asarray(frame.gravity_cam, dtype=np.float64)
        rot = gravity_aligned_rotation(gravity).astype(np.float32)
        pts_img = cam @ rot.T                                    # (h, w, 3) gravity-aligned
        normals_img = _normals(pts_img)
        refined = self._floor_gravity(pts_img, normals_img, rot)
        if refined is not None:                                  # re-express in the refined frame
            gravity = refined
            new_rot = gravity_aligned_rotation(gravity).astype(np.float32)
            delta = new_rot @ rot.T
            pts_img, normals_img = pts_img @ delta.T, normals_img @ delta.T
        frame = DetectorInput(frame.stamp_ns, frame.frame_id, frame.intrinsics, gravity,
                              frame.rgb, frame.depth)
        good = valid & np.all(np.isfinite(normals_img), axis=-1)
        pts = pts_img[good]
        nrm = normals_img[good]
        pix = np.stack([v[good], u[good]], -1)                  # full-resolution pixel coords
        if len(pts) < cfg.min_cluster_points:
            return Candidates(frame, None, None, [])

        structural, floor_z, ceiling_z, walls = self._structure(pts, nrm)
        obj = ~structural
        labels = self._clusters(pts[obj], nrm[obj])
        obj_idx = np.flatnonzero(obj)
        items = []
        rgb = frame.rgb
        margin = 2 * s
        for points, normals, pixels, support_z in self._split_supports(
                pts[obj], nrm[obj], pix[obj_idx], labels):
            hidden = self._bottom_hidden(pixels, frame.depth, s)
            fit = self._fit_box(points, normals, support_z, floor_z, walls, hidden)
            if fit is None or self._is_structure_remnant(fit[0], normals, ceiling_z):
                continue
            truncated = bool(pixels[:, 0].min() < margin or pixels[:, 1].min() < margin
                             or pixels[:, 0].max() >= intr.height - margin
                             or pixels[:, 1].max() >= intr.width - margin)
            items.append(Candidate(
                points, normals, pixels, rgb[pixels[:, 0], pixels[:, 1]] if rgb is not None else None,
                fit[0], fit[1], truncated, support_z is not None, hidden,
                [pixels[:, 1].min() - s / 2, pixels[:, 0].min() - s / 2,
                 pixels[:, 1].max() + s / 2, pixels[:, 0].max() + s / 2]))
        return Candidates(frame, floor_z, ceiling_z, items, walls)

    # ------------------------------------------------------------------ structure

    def _floor_gravity(self, pts_img, normals_img, rot):
        """Gravity from the floor plane when the floor is visible: the IMU's estimate is off
        by a degree or more on a moving camera; the floor's normal is exact. Returns the
        refined gravity in the camera frame, or None (no floor, or too far off to trust)."""
        cfg = self.config
        ok = np.all(np.isfinite(normals_img), axis=-1) & np.isfinite(pts_img[..., 2])
        pts, nrm = pts_img[ok], normals_img[ok]
        up = nrm[:, 2] > 0.9
        floor_z = _peak_height(pts[up, 2], lowest=True, min_count=max(100, int(0.05 * len(pts))))
        if floor_z is None:
            return None
        sel = up & (np.abs(pts[:, 2] - floor_z) < 0.08)
        if np.count_nonzero(sel) < 200:
            return None
        floor = pts[sel].astype(np.float64)
        centre = floor.mean(0)
        _, _, vt = np.linalg.svd(floor - centre, full_matrices=False)
        normal = vt[2] if vt[2][2] > 0 else -vt[2]
        if np.degrees(np.arccos(np.clip(normal[2], -1, 1))) > cfg.max_gravity_correction_deg:
            return None
        return -(rot.T.astype(np.float64) @ normal)          # "down" in the camera frame

    def _structure(self, pts, nrm):
        """Mask of floor / ceiling / wall points, the floor height (or None), walls."""
        cfg = self.config
        tol = np.full(len(pts), cfg.surface_tolerance_m)
        # floor and ceiling: far away, quantised depth scatters more
        tol_far = tol + cfg.depth_noise_per_m2 * np.sum(pts ** 2, axis=1)
        z = pts[:, 2]
        up = nrm[:, 2] > 0.9
        down = nrm[:, 2] < -0.9
        min_count = max(30, int(0.02 * len(pts)))
        floor_z = _peak_height(z[up], lowest=True, min_count=min_count)
        ceiling_z = _peak_height(z[down], lowest=False, min_count=min_count)
        structural = np.zeros(len(pts), dtype=bool)
        if floor_z is not None:
            structural |= z < floor_z + tol_far
        if ceiling_z is not None and (floor_z is None or ceiling_z > floor_z + 1.5):
            structural |= z > ceiling_z - tol_far
        walls = []
        rng = np.random.default_rng(cfg.seed)
        vertical = (np.abs(nrm[:, 2]) < 0.3) & ~structural
        for _ in range(cfg.max_walls):
            cand = np.flatnonzero(vertical & ~structural)
            if len(cand) < max(50, 0.03 * len(pts)):
                break
            wall = self._find_wall(pts, nrm, cand, structural, rng, tol)
            if wall is None:
                break
            normal, offset, inliers = wall
            walls.append((normal, offset))
            structural[inliers] = True
        return structural, floor_z, ceiling_z, walls

    @staticmethod
    def _is_structure_remnant(box, normals, ceiling_z) -> bool:
        """Pieces of wall or ceiling that survived plane removal: boxes reaching the
        ceiling, or tall, long and paper-thin vertical slabs."""
        top = box[2] + box[5] / 2
        if ceiling_z is not None and top > ceiling_z - 0.1:
            return True
        thin, long = min(box[3], box[4]), max(box[3], box[4])
        vertical = np.mean(np.abs(normals[:, 2]) < 0.3)
        return bool(thin < 0.08 and long > 1.2 and box[5] > 1.2 and vertical > 0.8)

    def _find_wall(self, pts, nrm, cand, structural, rng, tol_all):
        cfg = self.config
        if len(cand) > 2000:                    # score hypotheses on a sample
            cand = np.sort(rng.choice(cand, 2000, replace=False))
        scale = len(np.flatnonzero((np.abs(nrm[:, 2]) < 0.3) & ~structural)) / len(cand)
        xy = pts[cand, :2]
        n_xy = nrm[cand, :2]
        k = cfg.ransac_iterations
        i = rng.integers(len(cand), size=k)
        j = rng.integers(len(cand), size=k)
        d = xy[j] - xy[i]
        length = np.linalg.norm(d, axis=1)
        ok = length > 0.3
        if not np.any(ok):
            return None
        i, d, length = i[ok], d[ok], length[ok]
        normal = np.stack([-d[:, 1], d[:, 0]], -1) / length[:, None]      # (K, 2)
        offset = np.sum(normal * xy[i], axis=1)                           # n . p = offset
        tol = tol_all[cand][:, None]
        dist = np.abs(xy @ normal.T - offset)                             # (P, K)
        aligned = np.abs(n_xy @ normal.T) > 0.85
        count = np.sum((dist < tol) & aligned, axis=0)
        for best in np.argsort(-count)[:5]:
            if count[best] * scale < max(50, 0.03 * len(pts)):
                return None
            inl = cand[(dist[:, best] < tol[:, 0]) & aligned[:, best]]
            zr = np.percentile(pts[inl, 2], [5, 95])
            if zr[1] - zr[0] < cfg.wall_min_height_m:
                continue
            # refit the line by least squares on the inliers
            centre = pts[inl, :2].mean(0)
            _, _, vt = np.linalg.svd(pts[inl, :2] - centre, full_matrices=False)
            nb = vt[1]
            ob = float(nb @ centre)
            if ob < 0:                         # camera (origin) on the negative side
                nb, ob = -nb, -ob
            # a wall bounds the visible space: little lies behind it (beyond the plane)
            signed = pts[:, :2] @ nb - ob
            others = ~structural
            behind = np.count_nonzero(others & (signed > 3 * tol_all)) / max(np.count_nonzero(others), 1)
            if behind > cfg.wall_max_behind:
                continue
            inliers = (np.abs(signed) < tol_all) & (np.abs(nrm[:, :2] @ nb) > 0.7)
            inliers |= signed > -tol_all        # everything at or behind the wall plane
            return nb, ob, inliers & ~structural
        return None

    # ------------------------------------------------------------------ clusters

    def _clusters(self, pts, nrm):
        """Connected components of the occupied voxels; a label per point (0 = none)."""
        cfg = self.config
        if len(pts) == 0:
            return np.zeros(0, dtype=np.int64)
        lo = pts.min(0)
        idx = np.floor((pts - lo) / cfg.voxel_m).astype(np.int64)
        shape = idx.max(0) + 1
        if np.prod(shape) > 20_000_000:        # far outliers: clip the grid
            idx = np.minimum(idx, np.array([400, 400, 120]))
            shape = idx.max(0) + 1
        grid = np.zeros(shape, dtype=bool)
        grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
        return labels[idx[:, 0], idx[:, 1], idx[:, 2]]

    def _groups(self, labels):
        order = np.argsort(labels, kind='stable')
        for group in np.split(order, np.flatnonzero(np.diff(labels[order])) + 1):
            if len(group) and labels[group[0]] > 0:
                yield group

    def _support_height(self, p, n):
        """Height of the highest upward-facing surface with something standing on it.

        A surface needs ``support_min_points`` points at 2 m; fewer farther away, since the
        number of points on a surface falls with the square of its distance."""
        cfg = self.config
        z_up = p[n[:, 2] > 0.85, 2]
        distance = float(np.median(np.linalg.norm(p, axis=1)))
        min_points = max(5, int(round(cfg.support_min_points * min(1.0, (2.0 / max(distance, 0.1)) ** 2))))
        if len(z_up) < min_points:
            return None
        bin_m = 0.02
        lo = z_up.min()
        counts = np.bincount(((z_up - lo) / bin_m).astype(int))
        smooth = counts + np.r_[0, counts[:-1]] + np.r_[counts[1:], 0]
        for i in np.flatnonzero(smooth >= min_points)[::-1]:
            h = float(np.median(z_up[np.abs(z_up - (lo + (i + 0.5) * bin_m)) < 1.5 * bin_m]))
            if np.count_nonzero(p[:, 2] > h + cfg.surface_tolerance_m / 2) >= cfg.min_cluster_points // 2:
                return h
        return None

    def _split_supports(self, pts, nrm, pix, labels):
        """Yield (points, normals, pixels, support height or None) per object.

        A cluster holding an upward-facing surface with points above it is a support (a
        table, a cabinet) carrying objects: points outside the surface's footprint belong to
        neighbouring objects (a chair at the table) and are clustered separately; points
        above the surface inside its footprint are clustered again, each part standing on
        the surface.
        """
        cfg = self.config
        for group in self._groups(labels):
            if len(group) < cfg.min_cluster_points:
                continue
            p, n, px = pts[group], nrm[group], pix[group]
            h = self._support_height(p, n)
            if h is None:
                yield p, n, px, None
                continue
            top = (n[:, 2] > 0.85) & (np.abs(p[:, 2] - h) < cfg.surface_tolerance_m)
            inside = _in_footprint(p[:, :2], p[top, :2], margin=0.03)
            above = inside & (p[:, 2] > h + cfg.surface_tolerance_m / 2)
            support = inside & ~above
            if np.count_nonzero(support) >= cfg.min_cluster_points:
                yield p[support], n[support], px[support], None
            # The rest, clustered again: parts entirely above the surface stand on it;
            # parts reaching outside its footprint (a chair pushed under a table) stand on
            # the floor, including whatever of them rises above the surface.
            idx = np.flatnonzero(~support)
            if len(idx) < cfg.min_cluster_points // 2:
                continue
            for part in self._groups(self._clusters(p[idx], n[idx])):
                if len(part) >= cfg.min_cluster_points // 2:
                    sel = idx[part]
                    on_top = bool(np.all(above[sel]))
                    yield p[sel], n[sel], px[sel], (h if on_top else None)

    # ------------------------------------------------------------------ boxes

    def _bottom_hidden(self, pixels, depth, s) -> bool:
        """Whether the object's bottom is out of sight: below most of its lowest visible
        pixels (per image column) lies something nearer — an occluder — or the image border."""
        rows, cols = pixels[:, 0], pixels[:, 1]
        order = np.lexsort((-rows, cols))                       # per column, lowest pixel first
        first = order[np.r_[True, np.diff(cols[order]) != 0]]
        r, c = rows[first], cols[first]
        below = r + 2 * s
        inside = below < depth.shape[0]
        d_obj = depth[r, c]
        d_below = np.full(len(r), np.nan, np.float32)
        d_below[inside] = depth[below[inside], c[inside]]
        hidden = ~inside | (np.isfinite(d_below) & (d_below < d_obj - self.config.occluder_gap_m))
        return bool(np.mean(hidden) >= 0.5)

    def _fit_box(self, pts, nrm, support_z, floor_z, walls, bottom_hidden=False):
        cfg = self.config
        if len(pts) < cfg.min_cluster_points // 2:
            return None
        xy = pts[:, :2]
        centre = np.median(xy, axis=0)
        rel = xy - centre

        if len(rel) > 1500:                      # the footprint needs no more points
            rel = rel[np.linspace(0, len(rel) - 1, 1500).astype(int)]
        sample = rel[np.linspace(0, len(rel) - 1, min(len(rel), 300)).astype(int)]

        def extents(points, thetas):
            """Robust (1st-99th percentile) bounds along the axes rotated by each theta."""
            c, s = np.cos(thetas), np.sin(thetas)
            a = np.stack([points @ np.stack([c, s]), points @ np.stack([-s, c])], -1)  # (N, K, 2)
            lo, hi = percentiles(a, (1, 99))
            return lo, hi

        def best(points, thetas):
            lo, hi = extents(points, thetas)
            return int(np.argmin(np.prod(np.maximum(hi - lo, 0.01), axis=-1)))

        thetas = np.radians(np.arange(0, 90, 3.0))
        coarse = thetas[best(sample, thetas)]
        fine = coarse + np.radians(np.arange(-1.5, 1.6, 0.5))
        yaw = fine[best(rel, fine)]
        lo, hi = (b[0] for b in extents(rel, np.array([yaw])))
        z_lo, z_hi = percentiles(pts[:, 2], (0.5, 99.5))
        # amodal completion downwards: objects stand on their support or the floor
        if support_z is not None:
            z_lo = support_z
        elif floor_z is not None and (z_lo - floor_z < cfg.floor_snap_m or bottom_hidden):
            z_lo = floor_z
        c, s = np.cos(yaw), np.sin(yaw)
        axes = np.array([[c, s], [-s, c]])                      # box x, y axes in the BEV
        top_visible = np.count_nonzero(nrm[:, 2] > 0.9) >= 0.1 * len(pts)
        if not top_visible:
            lo, hi = self._complete_back(centre, axes, lo, hi, walls)
        size_xy = hi - lo
        mid = centre + axes.T @ ((lo + hi) / 2)
        size = np.array([size_xy[0], size_xy[1], z_hi - z_lo])
        if np.any(size < 0.03) or np.any(size[:2] > 4.0) or size[2] > 3.0:
            return None
        box = np.array([mid[0], mid[1], (z_lo + z_hi) / 2, size[0], size[1], size[2], yaw])
        support = 1.0 - np.exp(-len(pts) / 80.0)
        thin = min(1.0, size.min() / 0.08)
        return box, float(support * (0.5 + 0.5 * thin))

    def _complete_back(self, centre, axes, lo, hi, walls):
        """Extend the side facing away from the camera: to a wall within reach, else to the
        box's visible width (clipped to the amodal depth limits). The camera is at the origin
        of the gravity-aligned frame."""
        cfg = self.config
        lo, hi = lo.copy(), hi.copy()
        view = centre / max(np.linalg.norm(centre), 1e-6)      # from camera towards the box
        k = int(np.argmin(hi - lo))                             # the unseen depth is the thin side
        sign = np.sign(axes[k] @ view) or 1.0
        face = hi[k] if sign > 0 else lo[k]
        target = None
        for normal, offset in walls:
            denom = normal @ axes[k] * sign
            if abs(denom) < 0.5:
                continue
            start = centre + axes[k] * face
            dist = (offset - normal @ start) / denom
            if 0 <= dist <= cfg.wall_snap_m:
                target = face + sign * (dist - 0.02)
        depth_now = hi[k] - lo[k]
        amodal = float(np.clip(hi[1 - k] - lo[1 - k], cfg.amodal_min_depth_m, cfg.amodal_max_depth_m))
        if target is None and depth_now < amodal:
            target = face + sign * (amodal - depth_now)
        if target is not None:
            if sign > 0:
                hi[k] = max(hi[k], target)
            else:
                lo[k] = min(lo[k], target)
        return lo, hi

    # ------------------------------------------------------------------ embedding

    @staticmethod
    def _embedding(colours, box, floor_z) -> np.ndarray:
        """Appearance + shape descriptor (EMBEDDING_DIM), unit length."""
        parts = []
        if colours is not None and len(colours):
            c = colours.astype(np.float32) / 255.0
            mx, mn = c.max(1), c.min(1)
            sat = np.where(mx > 1e-6, (mx - mn) / np.maximum(mx, 1e-6), 0.0)
            r, g, b = c[:, 0], c[:, 1], c[:, 2]
            delta = np.maximum(mx - mn, 1e-6)
            hue = np.where(mx == r, ((g - b) / delta) % 6,
                           np.where(mx == g, (b - r) / delta + 2, (r - g) / delta + 4)) / 6.0
            hue_hist = np.bincount((hue * 12).astype(int) % 12, weights=sat, minlength=12)
            val_hist = np.bincount(np.minimum((mx * 4).astype(int), 3), minlength=4).astype(float)
            parts += [0.8 * hue_hist / max(len(c), 1), 0.5 * val_hist / max(len(c), 1),
                      0.8 * c.mean(0), [0.5 * float(np.std(mx))]]
        else:
            parts += [np.zeros(12), np.zeros(4), np.zeros(3), [0.0]]
        size = np.sort(box[3:6])
        height = (box[2] - box[5] / 2 - floor_z) if floor_z is not None else 0.0
        parts += [0.6 * np.log1p(size * 2), [0.3 * np.log1p(max(height, 0.0) * 2)]]
        vec = np.concatenate([np.ravel(p) for p in parts]).astype(np.float32)
        return vec / max(np.linalg.norm(vec), 1e-9)
