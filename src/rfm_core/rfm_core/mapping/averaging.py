"""Global 4-DoF poses from relative ones: yaw averaging, then translation averaging (paper 3.5).

Unknowns per keyframe k: the yaw theta_k of T_k_map (gravity is known, so rotation is 1-DoF)
and the camera centre c_k in the map frame (so T_k_map = (theta_k, -Rz(theta_k) c_k)). An
edge T_s_t (source s, target t) measures

    theta_s - theta_t = yaw_st                      (circular)
    c_t - c_s         = Rz(theta_s)^T t_st          (linear once the yaws are known)

Before a full solve, measurements that the view graph's triangles contradict are dropped
(:func:`cycle_inconsistent`: a wrong edge breaks every loop through it). Both stages start
from a spanning tree grown from the anchor, each keyframe placed where most of
its edges to already placed keyframes agree (a vote, so that an outlier edge on the tree
cannot throw a whole branch off). Yaw averaging is then Gauss-Newton on wrapped residuals
with robust (Cauchy) IRLS weights; translation averaging is a sparse linear
least-squares problem per axis with Cauchy IRLS weights (metric scale: boxes are metric).
Each is run for ``rounds`` rounds, dropping edges that disagree by more than
``max_yaw_residual_deg`` / ``max_translation_residual_m`` (never an edge no loop checks: only
the gyroscope's yaw can disagree with it, :func:`_bridges`); only the largest connected
component of the surviving edges is registered; an edge of few objects between views no
stream links (photos) does not alone join two parts of two keyframes or more
(:func:`_lone_joins`). The gauge is the component's first
keyframe (identity pose). A wrong edge the growth meets early can make the right ones look
wrong (a loop closure dropped for it), so where no loaded map is held the solve is grown
again from each of the heaviest edges it dropped, placed first; of the solutions that
register the same keyframes, the one of least robust cost over their edges wins (residuals
capped at the outlier thresholds: an edge dropped costs its weight's worth of an outlier).

:class:`IncrementalAverager` keeps the solution live: a new keyframe is placed by the same
vote from its edges and only a window of recent keyframes is re-solved (warm-started,
bounded cost); edges inside the window that disagree are dropped; a full re-solve runs when
``loop_min_edges`` edges to keyframes outside the window disagree (a loop closing over
drift), when another component outgrows the registered one, or every ``full_every``
keyframes.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from rfm_core.geometry import Pose4, circular_mean, wrap_angle
from rfm_core.mapping.uncertainty import KeyframeCovariances
from rfm_core.settings import constant, setting

__all__ = ['AveragingConfig', 'AveragingResult', 'average_poses', 'IncrementalAverager', 'agreement',
           'cycle_inconsistent', 'gyro_drift', 'largest_component']


@dataclass(frozen=True)
class AveragingConfig:
    rounds: int = setting(3, 'Outlier-removal rounds of each stage (yaw, then translation)', lo=1, hi=20, paper=3)
    max_yaw_residual_deg: float = setting(3.0, 'Drop edges whose yaw disagrees with the solution by more (deg)',
                                          lo=0.1, hi=180.0, paper=3.0)
    max_translation_residual_m: float = setting(0.10, 'Drop edges whose translation disagrees by more (m)',
                                                lo=0.001, hi=10.0, paper=0.10)
    yaw_scale_deg: float = constant(1.0, 'Robust (Cauchy) loss scale of yaw residuals (deg)', lo=0.01, hi=90.0)
    translation_scale_m: float = constant(0.03, 'Robust (Cauchy) loss scale of translation residuals (m)',
                                          lo=0.001, hi=10.0)
    iterations: int = constant(8, 'Gauss-Newton / IRLS iterations per round', lo=1, hi=100)
    window: int = setting(30, 'Incremental solve: keyframes re-solved per update', lo=1, hi=100000)
    full_every: int = setting(100, 'Incremental solve: a full re-solve every this many keyframes (0: only when a '
                              'loop closes)', lo=0, hi=100000)
    loop_min_edges: int = constant(2, 'Incremental solve: a full re-solve once this many edges to keyframes '
                                   'outside the window disagree', lo=1, hi=1000)
    gyro_yaw_weight: float = constant(10.0, "Weight of the gyroscope's yaw between consecutive keyframes of a "
                                      'stream, in verified objects (yaw only; 0: boxes alone)', lo=0.0, hi=1000.0)
    gyro_bias_sigma_dps: float = constant(0.5, "Prior std of the gyroscope's yaw drift (deg/s; a MEMS gyroscope's "
                                          'zero-rate offset): the drift the relative poses measure against it is '
                                          'taken out of its yaw edges', lo=1e-3, hi=10.0)
    gyro_drift_update_deg: float = constant(0.05, "The gyroscope's yaw edges are re-set when the drift's estimate "
                                            'moves them by more than this over the longest of them (deg)',
                                            lo=0.0, hi=10.0)
    points_edge_weight: float = constant(2.0, 'Weight of an edge no object verified (a keyframe placed on its depth '
                                         'points, or by its motion refined on them), in verified objects: on tuning '
                                         'walks they are as accurate as edges of two objects or more', lo=0.0,
                                         hi=1000.0)
    pose_sigma_deg: float = constant(1.8, 'Yaw error of a relative pose one verified object supports (deg): a '
                                     'measurement of averaging weight w has this / sqrt(w). The poses\' covariances '
                                     '(rfm/camera_pose); calibrated on tuning rooms', lo=1e-3, hi=90.0)
    pose_sigma_m: float = constant(0.05, '... and error per axis of its translation (m)', lo=1e-4, hi=10.0)
    pose_sigma_prior_dof: float = constant(10.0, "... pooled, as observations of exactly that noise, with the "
                                           "solution's residuals where they say the measurements are noisier",
                                           lo=1.0, hi=1e6)
    tilt_sigma_deg: float = constant(1.0, "Error of the camera's roll and pitch (the gravity estimate's; deg)",
                                     lo=1e-3, hi=90.0)
    cycle_min_loops: int = constant(2, 'Cycle check before each full solve: drop a measurement no triangle of '
                                    'keyframes through it agrees with and at least this many whose other two pairs '
                                    'close loops of their own contradict (0: no check)', lo=0, hi=100)
    cycle_tolerance: float = constant(2.0, '... a triangle agrees within this multiple of the outlier thresholds',
                                      lo=0.5, hi=20.0)
    cycle_max_loops: int = constant(12, '... triangles tried per pair of keyframes', lo=1, hi=1000)
    lone_join_min_inliers: int = constant(4, 'Two parts of the view graph of two keyframes or more each that a '
                                          'single edge between views no stream links (photos) would join are '
                                          'joined by it only where it rests on this many objects; else they need '
                                          'a second edge, which the residual checks hold against the first',
                                          lo=1, hi=100)
    max_seen_through: float = constant(
        0.10, 'An edge of fewer objects than lone_join_min_inliers between views no stream links is dropped where '
        "more than this share of the depth points each view, moved into the other by it, puts in space the other "
        "saw through: the other's surfaces across its view, a look-alike (over tuning photos right edges 0.05-0.09 "
        'at p95; 31 of 34 grossly wrong ones 0.10-0.61)', lo=0.0, hi=1.0)


@dataclass
class AveragingResult:
    poses: dict                              #: keyframe id -> Pose4 T_k_map (registered only)
    inlier_edges: np.ndarray                 #: (E,) bool over the input edges
    yaw_residual_deg: np.ndarray             #: (E,) NaN for edges outside the component
    translation_residual_m: np.ndarray
    seconds: float = 0.0


def _robust(residual, scale):
    """IRLS weights of the Cauchy loss: outliers (many scales off) lose almost all weight,
    which is safe because the initial poses come from a robust vote."""
    return 1.0 / (1.0 + (np.asarray(residual) / scale) ** 2)


def gyro_drift(seconds, residuals, weights, cfg: AveragingConfig) -> float:
    """The gyroscope's yaw drift (rad/s) that relative poses measure: each edge's yaw minus
    the gyroscope's between the same two keyframes (``residuals``, rad) against the time
    between them (``seconds``). A robust (Cauchy) fit through the origin, each residual of
    std ``pose_sigma_deg`` / sqrt(its ``weights``), under a zero-mean prior of std
    ``gyro_bias_sigma_dps`` (few or short edges leave the drift near zero; a wrong edge
    counts little)."""
    x, w = np.asarray(seconds, float), np.asarray(weights, float)
    y = wrap_angle(np.asarray(residuals, float))
    if not len(x):
        return 0.0
    var = np.radians(cfg.pose_sigma_deg) ** 2 / np.maximum(w, 1e-6)
    sigma = np.radians(cfg.gyro_bias_sigma_dps)
    grid = sigma * np.linspace(-4.0, 4.0, 161)           # the basin: least robust cost on a grid
    cost = np.log1p((y[None] - grid[:, None] * x[None]) ** 2 / var[None]).sum(1) + 0.5 * (grid / sigma) ** 2
    drift = float(grid[np.argmin(cost)])
    for _ in range(5):                                   # then IRLS
        a = 1.0 / (var + (y - drift * x) ** 2)
        drift = float(np.sum(a * x * y) / (np.sum(a * x * x) + 0.5 / sigma ** 2))
    return drift


def largest_component(nodes: np.ndarray, src: np.ndarray, dst: np.ndarray,
                      reference: np.ndarray | None = None, sizes: np.ndarray | None = None) -> np.ndarray:
    """Mask over ``nodes`` (indices 0..n-1) of the largest connected component of the edges;
    ties go to the component holding the lowest index. ``sizes``: how many keyframes each
    node stands for (itself and those culled into it; 1 each when not given), so that
    culling a component's keyframes does not shrink it. ``reference`` (a mask over the
    nodes: a loaded map's keyframes): the component holding the most of them, where one
    holds two or more, whatever its size (a second session does not take the map over)."""
    n = len(nodes)
    if n == 0:
        return np.zeros(0, bool)
    graph = sp.coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    counts = np.bincount(labels, weights=sizes)
    if reference is not None and np.any(reference):
        held = np.bincount(labels[reference], minlength=len(counts))
        if held.max() >= 2:
            counts = np.where(held == held.max(), counts, 0)
    best = np.flatnonzero(counts == counts.max())
    first = min(best, key=lambda lab: np.flatnonzero(labels == lab)[0])
    return labels == first


def _hypotheses(k, incident, src, dst, yaw, trans, theta, centres):
    """Pose hypotheses (yaw, centre) for node k from its edges to placed nodes."""
    hyp = []
    for i in incident:
        if src[i] == k:          # theta_k - theta_u = yaw;  c_u - c_k = R_k^T t
            u = dst[i]
            th = wrap_angle(theta[u] + yaw[i])
            c = centres[u] - Pose4(th, (0, 0, 0)).rotation.T @ trans[i]
        else:                    # theta_u - theta_k = yaw;  c_k - c_u = R_u^T t
            u = src[i]
            th = wrap_angle(theta[u] - yaw[i])
            c = centres[u] + Pose4(theta[u], (0, 0, 0)).rotation.T @ trans[i]
        hyp.append((th, c))
    return hyp


def agreement(yaws, centres, cfg: AveragingConfig) -> np.ndarray:
    """(n, n) bool: which pose hypotheses (yaws in rad, centres in m) agree within the outlier
    thresholds of averaging."""
    th = np.asarray(yaws, float)
    c = np.asarray(centres, float).reshape(len(th), 3)
    yaw_ok = np.degrees(np.abs(wrap_angle(th[:, None] - th[None, :]))) <= cfg.max_yaw_residual_deg
    return yaw_ok & (np.linalg.norm(c[:, None] - c[None, :], axis=-1) <= cfg.max_translation_residual_m)


def _vote(hyp, weights, cfg: AveragingConfig, yaw_hyp=(), yaw_weights=()):
    """The hypothesis most edge weight agrees with (within the outlier thresholds), refined
    as the weighted mean of its supporters. ``yaw_hyp``: yaws measured alone (the
    gyroscope's edges), which support the hypotheses whose yaw they agree with. Returns
    (yaw, centre, supporting weight)."""
    th = np.array([h[0] for h in hyp])
    c = np.array([h[1] for h in hyp])
    w = np.asarray(weights, float)
    agree = agreement(th, c, cfg)
    support = agree.astype(float) @ w
    if len(yaw_hyp):
        yaw_agree = np.degrees(np.abs(wrap_angle(th[:, None] - np.asarray(yaw_hyp)[None]))) <= cfg.max_yaw_residual_deg
        support = support + yaw_agree.astype(float) @ np.asarray(yaw_weights, float)
    # ties (hypotheses that each stand alone, say) go to the one nearest the others: the
    # weighted medoid, in units of the outlier thresholds, not the first edge's
    tied = np.flatnonzero(support >= support.max() - 1e-9)
    if len(tied) > 1:
        spread = np.maximum(np.degrees(np.abs(wrap_angle(th[tied, None] - th[None, :]))) / cfg.max_yaw_residual_deg,
                            np.linalg.norm(c[tied, None] - c[None, :], axis=-1) / cfg.max_translation_residual_m)
        best = int(tied[np.argmin(spread @ w)])
    else:
        best = int(tied[0])
    sup = agree[best]
    ws = w[sup]
    return circular_mean(th[sup], ws), (ws[:, None] * c[sup]).sum(0) / ws.sum(), float(support[best])


def _propagate(n, src, dst, yaw, trans, weight, root, cfg, theta=None, centres=None, placed=None, yaw_edges=None):
    """Robust initial poses: grow from the placed nodes (or ``root`` at identity), always
    placing next the node whose edges to placed nodes agree best (agreeing weight minus half
    the disagreeing weight), at the pose they agree on; a node whose edges disagree waits
    for more placed neighbours. ``yaw_edges`` (src, dst, yaw, weight) of the gyroscope vote
    on yaws too, but place nothing. Unreached nodes stay NaN."""
    import heapq  # noqa: PLC0415

    theta = np.full(n, np.nan) if theta is None else theta.copy()
    centres = np.full((n, 3), np.nan) if centres is None else centres.copy()
    placed = np.zeros(n, bool) if placed is None else placed.copy()
    if not np.any(placed):
        theta[root], centres[root] = 0.0, 0.0
        placed[root] = True
    adj = [[] for _ in range(n)]
    for i, (s, t) in enumerate(zip(src, dst)):
        adj[s].append(i)
        adj[t].append(i)
    ysrc, ydst, yyaw, yweight = yaw_edges if yaw_edges is not None else (np.zeros(0, int),) * 2 + (np.zeros(0),) * 2
    yadj = [[] for _ in range(n)]
    for i, (s, t) in enumerate(zip(ysrc, ydst)):
        yadj[s].append(i)
        yadj[t].append(i)
    votes, keys = {}, {}
    heap = []

    def refresh(v):
        incident = [i for i in adj[v] if placed[dst[i] if src[i] == v else src[i]]]
        gyro = [i for i in yadj[v] if placed[ydst[i] if ysrc[i] == v else ysrc[i]]]
        # theta_src - theta_dst = yaw
        gyro_yaws = [wrap_angle(theta[ydst[i]] + yyaw[i]) if ysrc[i] == v else wrap_angle(theta[ysrc[i]] - yyaw[i])
                     for i in gyro]
        votes[v] = _vote(_hypotheses(v, incident, src, dst, yaw, trans, theta, centres), weight[incident], cfg,
                         gyro_yaws, yweight[gyro])
        # agreement counts for a node, disagreement against it (placed last: more evidence)
        total = float(np.sum(weight[incident])) + float(np.sum(yweight[gyro]))
        key = votes[v][2] - 0.5 * (total - votes[v][2])
        keys[v] = key
        heapq.heappush(heap, (-key, int(v)))

    frontier = {int(dst[i] if src[i] == u else src[i]) for u in np.flatnonzero(placed) for i in adj[u]}
    for v in frontier:
        if not placed[v]:
            refresh(v)
    while heap:
        neg, v = heapq.heappop(heap)
        if placed[v] or -neg != keys[v]:
            continue
        theta[v], centres[v], _ = votes[v]
        placed[v] = True
        for i in adj[v]:
            u = dst[i] if src[i] == v else src[i]
            if not placed[u]:
                refresh(u)
        for i in yadj[v]:                   # a placed gyroscope neighbour changes the vote too
            u = ydst[i] if ysrc[i] == v else ysrc[i]
            if not placed[u] and u in keys:
                refresh(u)
    return theta, centres, placed


def _solve_yaw(theta, src, dst, yaw, weight, free, cfg: AveragingConfig):
    """Robust Gauss-Newton on wrapped yaw residuals; only ``free`` nodes move."""
    n = len(theta)
    theta = theta.copy()
    index = -np.ones(n, np.int64)
    index[free] = np.arange(np.count_nonzero(free))
    m = int(np.count_nonzero(free))
    if m == 0 or len(src) == 0:
        return theta
    delta = np.radians(cfg.yaw_scale_deg)
    rows = np.arange(len(src))
    for _ in range(cfg.iterations):
        r = wrap_angle(theta[src] - theta[dst] - yaw)
        w = weight * _robust(r, delta)
        a_src, a_dst = index[src], index[dst]
        data = np.r_[np.ones(np.count_nonzero(a_src >= 0)), -np.ones(np.count_nonzero(a_dst >= 0))]
        rr = np.r_[rows[a_src >= 0], rows[a_dst >= 0]]
        cc = np.r_[a_src[a_src >= 0], a_dst[a_dst >= 0]]
        jac = sp.csr_matrix((data, (rr, cc)), shape=(len(src), m))
        jw = jac.multiply(w[:, None]).tocsr()
        h = (jac.T @ jw).tocsc() + sp.identity(m, format='csc') * 1e-9
        step = -spsolve(h, jw.T @ r)
        theta[free] = wrap_angle(theta[free] + step)
        if np.max(np.abs(step)) < 1e-9:
            break
    return theta


def _solve_centres(theta, centres, src, dst, trans, weight, free, cfg: AveragingConfig):
    """Robust sparse least squares for camera centres; only ``free`` nodes move."""
    n = len(theta)
    centres = centres.copy()
    m = int(np.count_nonzero(free))
    if m == 0 or len(src) == 0:
        return centres
    index = -np.ones(n, np.int64)
    index[free] = np.arange(m)
    meas = _centre_offsets(theta[src], trans)
    a_src, a_dst = index[src], index[dst]
    rows = np.arange(len(src))
    data = np.r_[-np.ones(np.count_nonzero(a_src >= 0)), np.ones(np.count_nonzero(a_dst >= 0))]
    rr = np.r_[rows[a_src >= 0], rows[a_dst >= 0]]
    cc = np.r_[a_src[a_src >= 0], a_dst[a_dst >= 0]]
    jac = sp.csr_matrix((data, (rr, cc)), shape=(len(src), m))
    # the fixed nodes move to the right-hand side
    known = np.zeros((len(src), 3))
    known[a_src < 0] -= centres[src[a_src < 0]]
    known[a_dst < 0] += centres[dst[a_dst < 0]]
    rhs = meas - known
    x = centres[free]
    for _ in range(cfg.iterations):
        resid = jac @ x - rhs
        w = weight * _robust(np.linalg.norm(resid, axis=1), cfg.translation_scale_m)
        jw = jac.multiply(w[:, None]).tocsr()
        h = (jac.T @ jw).tocsc() + sp.identity(m, format='csc') * 1e-9
        new = spsolve(h, jw.T @ rhs).reshape(m, 3)
        done = np.max(np.abs(new - x)) < 1e-7
        x = new
        if done:
            break
    centres[free] = x
    return centres


def _centre_offsets(theta_src, trans):
    """c_t - c_s measured by the edges: Rz(theta_s)^T t_st, (E, 3)."""
    c, s = np.cos(theta_src), np.sin(theta_src)
    return np.stack([c * trans[:, 0] + s * trans[:, 1], -s * trans[:, 0] + c * trans[:, 1], trans[:, 2]], 1)


def _residuals(theta, centres, src, dst, yaw, trans):
    yaw_r = np.degrees(np.abs(wrap_angle(theta[src] - theta[dst] - yaw)))
    t_r = np.linalg.norm(centres[dst] - centres[src] - _centre_offsets(theta[src], trans), axis=1)
    return yaw_r, t_r


def _poses(theta, centres):
    return [Pose4.from_centre(float(th), ctr) for th, ctr in zip(theta, centres)]


def _pose_params(pose: Pose4):
    """(yaw, camera centre) of T_k_map."""
    return pose.yaw, -(pose.rotation.T @ pose.t)


def average_poses(ids, edges, config: AveragingConfig | None = None) -> AveragingResult:
    """Batch averaging. ``edges``: [(source id, target id, Pose4 T_source_target, weight), ...].

    Returns the registered poses (largest component after outlier removal) and per-edge
    inlier flags and residuals.
    """
    start = time.perf_counter()
    cfg = config or AveragingConfig()
    ids = list(ids)
    pos = {k: i for i, k in enumerate(ids)}
    n, e = len(ids), len(edges)
    src = np.array([pos[s] for s, _, _, _ in edges], np.int64)
    dst = np.array([pos[t] for _, t, _, _ in edges], np.int64)
    yaw = np.array([p.yaw for _, _, p, _ in edges], float)
    trans = np.array([p.t for _, _, p, _ in edges], float).reshape(e, 3)
    weight = np.array([w for *_, w in edges], float)
    theta, centres, active, comp, _ = _solve_all(n, src, dst, yaw, trans, weight, cfg)
    yaw_r = np.full(e, np.nan)
    t_r = np.full(e, np.nan)
    inside = comp[src] & comp[dst] if e else np.zeros(0, bool)
    if e:
        yr, tr = _residuals(theta, centres, src, dst, yaw, trans)
        yaw_r[inside], t_r[inside] = yr[inside], tr[inside]
    poses = {ids[k]: p for k, p in enumerate(_poses(theta, centres)) if comp[k]}
    return AveragingResult(poses, active & inside, yaw_r, t_r, time.perf_counter() - start)


# Pose4's ``@`` and ``inverse`` on (yaw, (3,) t) tuples: the cycle check composes a few per
# measurement, and building Pose4s made it 2.2x slower (1000 keyframes: 1.07 -> 2.37 s).
def _compose(a, b):
    """(yaw, t) of T_x_z = T_x_y @ T_y_z for 4-DoF poses a = T_x_y, b = T_y_z as (yaw, (3,) t)."""
    c, s = np.cos(a[0]), np.sin(a[0])
    tb = b[1]
    return a[0] + b[0], np.array([c * tb[0] - s * tb[1] + a[1][0], s * tb[0] + c * tb[1] + a[1][1], tb[2] + a[1][2]])


def _invert(a):
    c, s = np.cos(a[0]), np.sin(a[0])
    t = a[1]
    return -a[0], -np.array([c * t[0] + s * t[1], -s * t[0] + c * t[1], t[2]])


def _pair(a: int, b: int) -> tuple:
    """The key of an unordered pair of keyframes."""
    return (a, b) if a < b else (b, a)


def cycle_inconsistent(src, dst, yaw, trans, usable, cfg: AveragingConfig) -> np.ndarray:
    """(E,) bool: measurements the view graph's triangles contradict (cycle consistency).

    A triangle of keyframes (a, b, k) closes the measurement T_a_b with T_a_k @ T_k_b
    (any of the measurements of those pairs: a pair may be measured several times). A wrong
    edge breaks every triangle through it, a right one only those through a wrong partner.
    So a measurement is dropped when no triangle agrees with it and at least
    ``cycle_min_loops`` disagree whose two other pairs each close some triangle of their own
    (they are not the wrong ones). Only ``usable`` measurements take part. Poses are
    compared within ``cycle_tolerance`` times the averaging's outlier thresholds."""
    e = len(src)
    flagged = np.zeros(e, bool)
    if cfg.cycle_min_loops <= 0 or e < 3:
        return flagged
    yaw_tol = np.radians(cfg.cycle_tolerance * cfg.max_yaw_residual_deg)
    t_tol = cfg.cycle_tolerance * cfg.max_translation_residual_m
    pairs: dict = {}                       # (a, b), a < b -> [(edge, T_a_b as (yaw, t))]
    for i in np.flatnonzero(usable):
        a, b = int(src[i]), int(dst[i])
        if a == b:
            continue
        pose = (float(yaw[i]), np.asarray(trans[i], float))
        pairs.setdefault(_pair(a, b), []).append((int(i), pose if a < b else _invert(pose)))
    neighbours: dict = {}
    for a, b in pairs:
        neighbours.setdefault(a, set()).add(b)
        neighbours.setdefault(b, set()).add(a)

    def between(x, y):
        """The measurements of T_x_y."""
        measured = [p for _, p in pairs[_pair(x, y)][:4]]
        return measured if x < y else [_invert(p) for p in measured]

    def agrees(p, q):
        return (abs(wrap_angle(p[0] - q[0])) <= yaw_tol) and np.linalg.norm(p[1] - q[1]) <= t_tol

    closes = {}                            # pair -> whether any triangle through it agrees
    verdicts = {}                          # edge -> [(agrees, k)]
    for (a, b), measured in pairs.items():
        common = sorted(neighbours[a] & neighbours[b])[:cfg.cycle_max_loops]
        loops = [(k, [_compose(p, q) for p in between(a, k) for q in between(k, b)]) for k in common]
        for i, pose in measured:
            verdicts[i] = [(any(agrees(pose, c) for c in closed), k) for k, closed in loops]
            closes[(a, b)] = closes.get((a, b), False) or any(ok for ok, _ in verdicts[i])
    for (a, b), measured in pairs.items():
        for i, _ in measured:
            loops = verdicts[i]
            if any(ok for ok, _ in loops):
                continue
            confirmed = sum(closes[_pair(a, k)] and closes[_pair(k, b)] for _, k in loops)
            flagged[i] = confirmed >= cfg.cycle_min_loops
    return flagged


#: a full solve starts again from at most this many of the edges it dropped
_RESTARTS = 2


def _robust_cost(theta, centres, comp, src, dst, yaw, trans, weight, full, cfg: AveragingConfig) -> float:
    """The robust (Cauchy) cost of a solution over the edges inside its component, each
    residual capped at the outlier thresholds (an edge dropped, however far off, costs its
    weight's worth of an outlier): how solutions of the same component from different starts
    compare."""
    inside = comp[src] & comp[dst]
    yr, tr = _residuals(np.where(comp, theta, 0.0), np.where(comp[:, None], centres, 0.0), src, dst, yaw, trans)
    yr = np.minimum(yr, cfg.max_yaw_residual_deg)
    tr = np.minimum(tr, cfg.max_translation_residual_m)
    cost = np.log1p((yr / cfg.yaw_scale_deg) ** 2) + np.where(full, np.log1p((tr / cfg.translation_scale_m) ** 2), 0.0)
    return float(np.sum((weight * cost)[inside]))


def _bridges(candidates, edges, src, dst, n) -> np.ndarray:
    """Which of the ``candidates`` (edge indices) are full edges of ``edges`` (a mask) that no
    loop of them checks: removing one disconnects its two keyframes. Such an edge is never
    dropped as an outlier: only the gyroscope's yaw-only edges can disagree with it, and they
    outvote its yaw but place no keyframe, so dropping it would only split the map (a robot's
    odometry chaining keyframes past a bare wall, its yaw a few degrees off the gyroscope's)."""
    out = np.zeros(len(candidates), bool)
    for j, i in enumerate(candidates):
        if not edges[i]:
            continue
        labels = _components_without(i, edges, src, dst, n)
        out[j] = labels[src[i]] != labels[dst[i]]
    return out


def _components_without(i, edges, src, dst, n) -> np.ndarray:
    """(n,) component labels of the keyframes joined by ``edges`` (a mask) less edge ``i``."""
    keep = edges.copy()
    keep[i] = False
    graph = sp.coo_matrix((np.ones(int(keep.sum())), (src[keep], dst[keep])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _lone_joins(links, lone, src, dst, n) -> np.ndarray:
    """Mask over the edges: those of ``lone`` among ``links`` (masks) that alone join two parts
    of two keyframes or more each (removing one leaves its keyframes apart, both in such a part).
    A keyframe hanging on one edge is not such a part: a wrong edge misplaces it alone."""
    out = np.zeros(len(src), bool)
    for i in np.flatnonzero(links & lone):
        labels = _components_without(i, links, src, dst, n)
        a, b = labels[src[i]], labels[dst[i]]
        if a != b:
            counts = np.bincount(labels)
            out[i] = counts[a] >= 2 and counts[b] >= 2
    return out


def _solve_all(n, src, dst, yaw, trans, weight, cfg, anchor_order=None, yaw_only=None, reference=None,
               fixed=None, sizes=None, lone=None):
    """Full robust solve. Returns theta, centres (NaN outside the component), active edge
    mask, component mask, and the mask of the edges the cycle check dropped. ``yaw_only``
    edges (the gyroscope's) count in the yaw stage only: they neither place nor connect
    keyframes. ``reference``, ``sizes``: see :func:`largest_component`. ``fixed`` (theta, centres):
    the reference keyframes' poses (NaN elsewhere), held where they are: the rest grows from
    and is solved around them."""
    active = np.ones(len(src), bool)
    full = ~yaw_only if yaw_only is not None else np.ones(len(src), bool)
    theta = np.full(n, np.nan)
    centres = np.full((n, 3), np.nan)
    comp = np.zeros(n, bool)
    cycle = np.zeros(len(src), bool)
    if n == 0:
        return theta, centres, active, comp, cycle
    order = np.arange(n) if anchor_order is None else np.asarray(anchor_order, np.int64)
    held = np.zeros(n, bool) if fixed is None else np.isfinite(fixed[0])
    between_held = held[src] & held[dst]        # the loaded map's own: they hold it together, nothing moves them
    cycle = cycle_inconsistent(src, dst, yaw, trans, active & full, cfg) & ~between_held
    active &= ~cycle

    def component(active, seed=None):
        """The component to register, and the keyframe it is grown from: the first in
        ``order`` (the anchor), or the source of the ``seed`` edge where it is in it."""
        links = active & full
        if lone is not None and np.any(links & lone):
            links = links & ~_lone_joins(links, lone, src, dst, n)
        c = largest_component(np.arange(n), src[links], dst[links], reference, sizes)
        if seed is not None and c[src[seed]] and c[dst[seed]]:
            return c, int(src[seed])
        return c, int(next(k for k in order if c[k]))

    def gyro(mask):
        u = mask & ~full
        return src[u], dst[u], yaw[u], weight[u]

    def start(comp, root, active, seed=None):
        use = active & full & comp[src] & comp[dst]
        hold = held & comp
        if not np.any(hold):
            th0 = c0 = placed = None
            if seed is not None and root == src[seed]:      # the seed edge places its target first
                placed = np.zeros(n, bool)
                placed[[src[seed], dst[seed]]] = True
                th0, c0 = np.full(n, np.nan), np.full((n, 3), np.nan)
                th0[root], c0[root] = 0.0, 0.0
                (th0[dst[seed]], c0[dst[seed]]), = _hypotheses(dst[seed], [seed], src, dst, yaw, trans, th0, c0)
            return _propagate(n, src[use], dst[use], yaw[use], trans[use], weight[use], root, cfg, th0, c0, placed,
                              yaw_edges=gyro(active & comp[src] & comp[dst]))[:2]
        return _propagate(n, src[use], dst[use], yaw[use], trans[use], weight[use], root, cfg,
                          np.where(hold, fixed[0], np.nan), np.where(hold[:, None], fixed[1], np.nan), hold,
                          yaw_edges=gyro(active & comp[src] & comp[dst]))[:2]

    def rounds(active, seed=None):
        comp, root = component(active, seed)
        theta, centres = start(comp, root, active, seed)
        for stage in ('yaw', 'translation'):
            for _ in range(max(cfg.rounds, 1)):
                use = active & comp[src] & comp[dst]
                if stage == 'translation':
                    use &= full
                free = comp & ~held
                free[root] = False
                if stage == 'yaw':
                    theta = _solve_yaw(np.where(comp, theta, 0.0), src[use], dst[use], yaw[use], weight[use],
                                       free, cfg)
                    yr, _ = _residuals(theta, np.zeros((n, 3)), src, dst, yaw, trans)
                    bad = use & (yr > cfg.max_yaw_residual_deg)
                    bad[np.flatnonzero(bad)[_bridges(np.flatnonzero(bad), use & full, src, dst, n)]] = False
                else:
                    centres = _solve_centres(theta, np.where(comp[:, None], centres, 0.0), src[use], dst[use],
                                             trans[use], weight[use], free, cfg)
                    _, tr = _residuals(theta, centres, src, dst, yaw, trans)
                    bad = use & (tr > cfg.max_translation_residual_m)
                bad &= ~between_held
                if not np.any(bad):
                    break
                active = active & ~bad
                new_comp, new_root = component(active, seed if seed is not None and active[seed] else None)
                if new_root != root:            # the root left the component: re-initialise it
                    theta, centres = start(new_comp, new_root, active)
                comp, root = new_comp, new_root
        return theta, centres, active, comp

    # grown from the anchor; where nothing is held, also from each of the heaviest edges that
    # solution dropped, placed first: a wrong edge met early in the growth can make the right
    # ones look wrong. Of the solutions that register the anchor's keyframes, the one of least
    # robust cost over their edges wins (a restart does not join keyframes the anchor's solution
    # left out: it would join them through an edge that solution found wrong).
    def scored(found):
        return _robust_cost(*found[:2], found[3], src, dst, yaw, trans, weight, full, cfg), found

    best = scored(rounds(active))
    if fixed is None:
        dropped = np.flatnonzero(active & full & ~best[1][2] & best[1][3][src] & best[1][3][dst])
        for seed in dropped[np.argsort(-weight[dropped], kind='stable')][:_RESTARTS]:
            found = scored(rounds(active, int(seed)))
            if np.array_equal(found[1][3], best[1][3]) and found[0] < best[0]:
                best = found
    theta, centres, active, comp = best[1]
    if fixed is None and np.any(comp):          # the gauge: the anchor at identity
        anchor = next(k for k in order if comp[k])
        theta, centres = _regauge(theta, centres, anchor, 0.0, np.zeros(3))
    theta = np.where(comp, theta, np.nan)
    centres = np.where(comp[:, None], centres, np.nan)
    return theta, centres, active, comp, cycle


_EDGE_ARRAYS = ('_src', '_dst', '_yaw', '_trans', '_weight', '_active', '_yaw_only')


class _EdgeStore:
    """Edges in growable NumPy buffers (amortised O(1) append, O(1) array views)."""

    def __init__(self):
        self.n = 0
        self._src = np.zeros(64, np.int64)
        self._dst = np.zeros(64, np.int64)
        self._yaw = np.zeros(64)
        self._trans = np.zeros((64, 3))
        self._weight = np.zeros(64)
        self._active = np.zeros(64, bool)
        self._yaw_only = np.zeros(64, bool)

    def append(self, s, t, yaw, trans, weight, yaw_only=False):
        if self.n == len(self._src):
            for name in _EDGE_ARRAYS:
                old = getattr(self, name)
                setattr(self, name, np.concatenate([old, np.zeros_like(old)]))
        i = self.n
        self._src[i], self._dst[i], self._yaw[i] = s, t, yaw
        self._trans[i], self._weight[i], self._active[i] = trans, weight, True
        self._yaw_only[i] = yaw_only
        self.n += 1

    src = property(lambda self: self._src[:self.n])
    dst = property(lambda self: self._dst[:self.n])
    yaw = property(lambda self: self._yaw[:self.n])
    trans = property(lambda self: self._trans[:self.n])
    weight = property(lambda self: self._weight[:self.n])
    active = property(lambda self: self._active[:self.n])
    yaw_only = property(lambda self: self._yaw_only[:self.n])

    def __len__(self):
        return self.n


@dataclass
class UpdateStats:
    kind: str = 'none'                       #: none | local | full
    seconds: float = 0.0
    registered: int = 0
    edges_rejected: int = 0


@dataclass
class IncrementalAverager:
    """Live averaging: feed keyframes and edges, call :meth:`update`, read :attr:`poses`."""

    config: AveragingConfig = field(default_factory=AveragingConfig)

    def __post_init__(self):
        self.ids: list = []                  # keyframe ids in arrival order
        self._index: dict = {}
        self.edges = _EdgeStore()
        self._theta = np.zeros(0)
        self._centres = np.zeros((0, 3))
        self._registered = np.zeros(0, bool)
        self._new: list = []
        self._new_edges = False
        self._solved_edges = 0               # edges added before the last update (the later ones are new)
        self._since_full = 0
        self._needs_full = False
        self._loop_votes = 0
        self.cycle_dropped = 0               # edges the last full solve's cycle check dropped
        self.frame_changes = 0               # full solves whose registered part shares no keyframe with the last's
        self.stats = UpdateStats()
        self.reference: set = set()          # a loaded map's keyframes: their component stays the map
        self.sizes: dict = {}                # keyframe id -> keyframes it stands for (culled ones merged into it; 1 if absent)
        self.last_seen = None                # the newest frame placed in the registered part (a FrameTrack: keyframe_id, pose)
        self.lone_edges = None               # () -> (E,) bool: edges too weak to join two parts alone (_lone_joins)

    # ------------------------------------------------------------------ input

    def add_keyframe(self, keyframe_id: int) -> None:
        if keyframe_id in self._index:
            return
        self._index[keyframe_id] = len(self.ids)
        self.ids.append(keyframe_id)
        self._theta = np.r_[self._theta, np.nan]
        self._centres = np.r_[self._centres, np.full((1, 3), np.nan)]
        self._registered = np.r_[self._registered, False]
        self._new.append(keyframe_id)

    def add_edge(self, source_id: int, target_id: int, pose: Pose4, weight: float = 1.0,
                 yaw_only: bool = False) -> None:
        """An edge T_source_target; unknown keyframes are added. ``yaw_only``: only the yaw
        is measured (the gyroscope's rotation between two keyframes): it counts in yaw
        averaging but neither places nor connects keyframes."""
        for k in (source_id, target_id):
            self.add_keyframe(k)
        s, t = self._index[source_id], self._index[target_id]
        if s == t:
            return
        self.edges.append(s, t, float(pose.yaw), np.zeros(3) if yaw_only else np.asarray(pose.t, float),
                          float(weight), yaw_only)
        self._new_edges = True

    def set_yaw(self, index: int, yaw: float) -> None:
        """Replace the yaw an edge (by the order added) measures: a yaw-only edge's, once
        the gyroscope's drift is better known."""
        self.edges.yaw[index] = yaw
        self._new_edges = True

    # ------------------------------------------------------------------ output

    @property
    def poses(self) -> dict:
        """keyframe id -> Pose4 T_k_map of the registered keyframes."""
        out = {}
        for k in np.flatnonzero(self._registered):
            th, c = self._theta[k], self._centres[k]
            out[self.ids[k]] = Pose4.from_centre(float(th), c)
        return out

    @property
    def num_registered(self) -> int:
        """How many keyframes are registered (:attr:`poses` without building it)."""
        return int(self._registered.sum())

    def pose(self, keyframe_id: int) -> Pose4 | None:
        k = self._index.get(keyframe_id)
        if k is None or not self._registered[k]:
            return None
        th, c = self._theta[k], self._centres[k]
        return Pose4.from_centre(float(th), c)

    def covariances(self) -> KeyframeCovariances:
        """The current solution's keyframe pose covariances (:mod:`rfm_core.mapping.uncertainty`;
        called with a keyframe id), the first registered keyframe by id holding the map frame."""
        e, cfg = self.edges, self.config
        reg = np.flatnonzero(self._registered)
        anchor = int(reg[np.argmin(np.asarray(self.ids)[reg])]) if len(reg) else -1
        theta, centres = self._theta, self._centres
        residual_yaw = wrap_angle(theta[e.src] - theta[e.dst] - e.yaw)
        residual_t = centres[e.dst] - centres[e.src] - _centre_offsets(theta[e.src], e.trans)
        return KeyframeCovariances(theta, centres, e.src, e.dst, e.trans, e.weight, e.yaw_only, e.active,
                                   residual_yaw, residual_t, anchor, np.radians(cfg.pose_sigma_deg),
                                   cfg.pose_sigma_m, cfg.pose_sigma_prior_dof, dict(self._index))

    def kept_edges_of(self, keyframe_id: int) -> np.ndarray:
        """Indices (in the order added) of the edges the current solution keeps that touch
        one keyframe (yaw-only edges aside)."""
        i, e = self._index.get(keyframe_id), self.edges
        if i is None:
            return np.zeros(0, np.int64)
        return np.flatnonzero(((e.src == i) | (e.dst == i)) & e.active & ~e.yaw_only)

    def active_edges(self) -> list:
        """[(source id, target id)] of the edges the current solution keeps (yaw-only
        edges aside)."""
        e = self.edges
        keep = e.active & ~e.yaw_only
        return [(self.ids[a], self.ids[b]) for a, b in zip(e.src[keep], e.dst[keep])]

    # ------------------------------------------------------------------ solving

    def _arrays(self):
        e = self.edges
        return e.src, e.dst, e.yaw, e.trans, e.weight

    def update(self, force_full: bool = False) -> UpdateStats:
        """Fold in the keyframes and edges added since the last call."""
        start = time.perf_counter()
        cfg = self.config
        kind = 'none'
        if self._new or self._new_edges or force_full or self._needs_full:
            self._since_full += len(self._new)
            full = (force_full or self._needs_full or not np.any(self._registered)
                    or (cfg.full_every and self._since_full >= cfg.full_every)
                    or self._outgrown())
            if full:
                self._full()
                kind = 'full'
            else:
                kind = 'local' if self._local() else 'full'
            self._new = []
            self._new_edges = False
            self._solved_edges = len(self.edges)
        self.stats = UpdateStats(kind, time.perf_counter() - start, int(self._registered.sum()),
                                 int(np.count_nonzero(~self.edges.active)))
        return self.stats

    def restore(self, poses: dict, active, fold: bool = True) -> None:
        """Set the solution (e.g. from a map file) without solving: ``poses`` {id: Pose4
        T_k_map} of the registered keyframes, ``active`` whether each edge (in the order
        added) is kept; yaw-only edges always are. Keyframes and edges must have been added
        (``fold``: solved first, as pending input; else taken as solved by ``poses``)."""
        if fold:
            self.update()                        # fold pending input first, then overwrite
        self._new, self._new_edges = [], False
        self._solved_edges = len(self.edges)
        e = self.edges
        e.active[:] = np.asarray(active, bool).reshape(len(e)) | e.yaw_only
        self._registered[:] = False
        self._theta[:] = np.nan
        self._centres[:] = np.nan
        for k, pose in poses.items():
            i = self._index.get(k)
            if i is not None:
                self._theta[i], self._centres[i] = _pose_params(pose)
                self._registered[i] = True
        self._since_full = 0
        self._needs_full = False
        self._loop_votes = 0

    def _outgrown(self) -> bool:
        """Whether the keyframes outside the registered component (with edges among
        themselves) outnumber it: then another component may be the largest."""
        if not len(self.edges) or self._holds_reference():
            return False
        src, dst = self._arrays()[:2]
        src, dst = src[~self.edges.yaw_only], dst[~self.edges.yaw_only]
        linked = np.zeros(len(self.ids), bool)
        linked[src] = linked[dst] = True
        sizes = self._sizes()
        return sizes[linked & ~self._registered].sum() > sizes[self._registered].sum()

    def _sizes(self) -> np.ndarray:
        """How many keyframes each keyframe (by index) stands for (:attr:`sizes`)."""
        return np.array([self.sizes.get(k, 1) for k in self.ids], np.float64)

    def _holds_reference(self) -> bool:
        """Whether the registered component holds keyframes of a loaded map (it stays the map)."""
        return any(self._registered[self._index[k]] for k in self.reference if k in self._index)

    def _solve(self):
        """A full solve, in the previous gauge.

        Solved in a canonical order (keyframes by id, edges by their keyframes' ids and
        measurement), not in arrival order: keyframes and edges come on two topics, and an
        edge that arrives before its keyframe adds it, so the order (which breaks the
        placement vote's ties and picks the cycle check's triangles) made the map of the same
        messages depend on their timing."""
        src, dst, yaw, trans, weight = self._arrays()
        ids = np.asarray(self.ids, np.int64)
        node = np.argsort(ids, kind='stable')               # canonical position -> index
        rank = np.empty_like(node)
        rank[node] = np.arange(len(node))                    # index -> canonical position
        edge = np.lexsort((weight, trans[:, 2], trans[:, 1], trans[:, 0], yaw, self.edges.yaw_only,
                           ids[dst], ids[src]))
        # anchor: the earliest registered keyframe (by id) keeps the map frame stable
        reg = self._registered[node]
        order = np.r_[np.flatnonzero(reg), np.flatnonzero(~reg)]
        reference = np.array([k in self.reference for k in ids[node]], bool) if self.reference else None
        fixed, hold = None, np.zeros(len(node), bool)
        if reference is not None:           # held where they are (registered: the loaded map's poses)
            hold = reference & self._registered[node]
            fixed = (np.where(hold, self._theta[node], np.nan), np.where(hold[:, None], self._centres[node], np.nan))
        theta, centres, active, comp, cycle = _solve_all(
            len(self.ids), rank[src][edge], rank[dst][edge], yaw[edge], trans[edge], weight[edge], self.config,
            order, self.edges.yaw_only[edge], reference, fixed, self._sizes()[node],
            None if self.lone_edges is None else np.asarray(self.lone_edges(), bool)[edge])
        anchor = next((node[k] for k in order if comp[k]), None)
        held = bool(np.any(hold & comp))    # (canonical order, as comp is here)
        back = np.empty_like(edge)
        back[edge] = np.arange(len(edge))                    # store index -> canonical position
        theta, centres, comp = theta[rank], centres[rank], comp[rank]
        active, cycle = active[back], cycle[back]
        self.cycle_dropped = int(np.count_nonzero(cycle))
        if held:
            return theta, centres, active, comp     # a loaded map's keyframes, held where saved, are the gauge
        if np.any(self._registered & comp):
            # keep the previous gauge: express the new solution relative to the anchor's old pose
            if self._registered[anchor]:
                theta, centres = _regauge(theta, centres, anchor, self._theta[anchor], self._centres[anchor])
        elif np.any(self._registered) and np.any(comp):
            # another part of the graph outgrew the registered one and nothing joins them: the
            # map frame is now that part's, and poses given out before are in a frame that is gone
            self.frame_changes += 1
            link = self._gyroscope_link(comp)
            if link is not None:
                theta, centres = _regauge(theta, centres, *link)
        return theta, centres, active, comp

    def _gyroscope_link(self, comp):
        """Where the gyroscope puts a part of the graph that takes the map over (``comp``, by
        index) in the frame it takes over: (keyframe index, yaw, centre) from the newest
        gyroscope edge between the two parts, its yaw measured and its centre where the camera
        was last seen in the old part (:attr:`last_seen`, else that edge's keyframe there: the
        walk since is unknown); None without one."""
        e = self.edges
        old, new = self._registered[e.src] & comp[e.dst], comp[e.src] & self._registered[e.dst]
        link = np.flatnonzero(e.yaw_only & (old | new))
        if not len(link):
            return None
        i = link[np.argmax(np.maximum(e.src[link], e.dst[link]))]
        a, b = (e.src[i], e.dst[i]) if old[i] else (e.dst[i], e.src[i])
        yaw = self._theta[a] - e.yaw[i] if old[i] else self._theta[a] + e.yaw[i]      # theta_src - theta_dst = yaw
        centre = self._centres[a].copy()
        seen = self._index.get(self.last_seen.keyframe_id) if self.last_seen is not None else None
        if seen is not None and self._registered[seen]:
            t_map_k = Pose4.from_centre(float(self._theta[seen]), self._centres[seen]).inverse()
            centre = (t_map_k @ self.last_seen.pose).t                          # T_map_k T_k_camera
        return int(b), float(wrap_angle(yaw)), centre

    def _full(self):
        theta, centres, active, comp = self._solve()
        self.edges.active[:] = active
        self._theta, self._centres, self._registered = theta, centres, comp
        self._since_full = 0
        self._needs_full = False
        self._loop_votes = 0

    def _local(self) -> bool:
        """Register the new keyframes from their edges and re-solve a window around them.
        Returns False when it fell back to a full solve."""
        cfg = self.config
        src, dst, yaw, trans, weight = self._arrays()
        n = len(self.ids)
        theta, centres = self._theta.copy(), self._centres.copy()
        registered = self._registered.copy()
        active = self.edges.active.copy()
        full = ~self.edges.yaw_only
        self._revote(registered, active, src, dst, full)
        # place new keyframes from their edges to registered ones (robust vote)
        # (edges with an unregistered end: a chain of new keyframes is placed link by link)
        use = active & full & ~(registered[src] & registered[dst])
        if np.any(registered) and np.any(use):
            gyro = active & ~full & ~(registered[src] & registered[dst])
            theta, centres, registered = _propagate(n, src[use], dst[use], yaw[use], trans[use], weight[use],
                                                    None, cfg, theta, centres, registered,
                                                    yaw_edges=(src[gyro], dst[gyro], yaw[gyro], weight[gyro]))
        # window: the latest registered keyframes (by arrival) plus the new ones
        free = self._window(registered, [self._index[k] for k in self._new if registered[self._index[k]]])
        use = active & registered[src] & registered[dst] & (free[src] | free[dst])
        if not np.any(use):
            self._theta, self._centres, self._registered = theta, centres, registered
            return True
        theta = _solve_yaw(theta, src[use], dst[use], yaw[use], weight[use], free, cfg)
        ut = use & full
        centres = _solve_centres(theta, centres, src[ut], dst[ut], trans[ut], weight[ut], free, cfg)
        yr, tr = _residuals(theta, centres, src[use], dst[use], yaw[use], trans[use])
        bad = (yr > cfg.max_yaw_residual_deg) | ((tr > cfg.max_translation_residual_m) & full[use])
        idx = np.flatnonzero(use)[bad]
        idx = idx[~_bridges(idx, active & full & registered[src] & registered[dst], src, dst, n)]
        inside = free[src[idx]] & free[dst[idx]]
        self.edges.active[idx[inside]] = False     # local outliers: drop
        # edges to keyframes outside the window that the window cannot explain: a loop
        # closing over drift (several agree) or outliers; a full solve decides
        self._loop_votes += int(np.count_nonzero(~inside))
        self._theta, self._centres, self._registered = theta, centres, registered
        if self._loop_votes >= cfg.loop_min_edges:
            self._full()
            return False
        return True

    def _window(self, registered, also=()) -> np.ndarray:
        """(n,) bool: the keyframes a local solve moves: the latest ``window`` registered ones
        (by arrival) and ``also`` (indices), never the anchor (the first keyframe registered
        before this update) or a loaded map's keyframes."""
        free = np.zeros(len(self.ids), bool)
        free[np.flatnonzero(registered)[-self.config.window:]] = True
        free[list(also)] = True
        anchor = np.flatnonzero(self._registered)
        if len(anchor):
            free[anchor[0]] = False
        free[[self._index[k] for k in self.reference if k in self._index]] = False     # a loaded map holds
        return free

    def _revote(self, registered, active, src, dst, full) -> None:
        """Keyframes of the window that new edges reach, placed before from fewer of their
        edges, are placed again (``registered`` cleared in place, their edges to registered
        keyframes active again) by the vote over all of them: a keyframe's edges arrive as
        separate messages, and a solve between two of them must not make the first the judge
        of the rest (its residual check would drop the later ones, which agree with each
        other, as outliers of a keyframe one wrong edge placed). The newer end of each new
        edge (by arrival) is placed again; never the anchor or a loaded map's keyframe."""
        new = np.arange(self._solved_edges, len(self.edges))
        new = new[full[new]]
        if not len(new):
            return
        again = np.maximum(src[new], dst[new])
        again = np.unique(again[self._window(registered)[again]])
        if not len(again):
            return
        registered[again] = False
        touch = np.isin(src, again) | np.isin(dst, again)
        back = touch & full & (registered[src] | registered[dst])
        active[back] = True
        self.edges.active[back] = True


def _regauge(theta, centres, anchor, old_theta, old_centre):
    """Rigidly move a solution so that ``anchor`` has its old yaw and centre."""
    d = wrap_angle(old_theta - theta[anchor])
    # T_k_map' = T_k_map @ G^-1 with G mapping the new map frame to the old: yaw' = yaw + d ...
    # centres rotate by -d about the anchor's centre and shift onto the old centre
    rot = Pose4(-d, (0, 0, 0)).rotation
    new_centres = (centres - centres[anchor]) @ rot.T + old_centre
    return wrap_angle(theta + d), new_centres
