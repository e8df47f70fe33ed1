"""Pose covariances (rfm_core.mapping.uncertainty) against the spread of the poses themselves."""
import numpy as np

from rfm_core.geometry import Pose4, wrap_angle
from rfm_core.mapping.averaging import AveragingConfig, IncrementalAverager
from rfm_core.mapping.uncertainty import frame_covariance, relative_covariance, ros_pose_covariance


def _params(pose: Pose4) -> np.ndarray:
    """(theta, camera centre) of T_k_map."""
    return np.r_[pose.yaw, -(pose.rotation.T @ np.asarray(pose.t))]


def _averaged(rng, pairs, noise: float, draws: int):
    """Eight keyframes; ``draws`` times, relative poses drawn with ``noise`` times the noise
    their weights state, averaged: (the poses' (theta, centre) per draw, the covariances
    each draw's solution gives)."""
    n = 8
    theta = np.r_[0.0, rng.uniform(-np.pi, np.pi, n - 1)]
    centres = np.r_[[np.zeros(3)], rng.uniform(-2.0, 2.0, (n - 1, 3)) * [1, 1, 0.1]]
    truth = [Pose4.from_centre(th, c) for th, c in zip(theta, centres)]
    weights = {p: float(rng.choice([2.0, 3.0, 5.0])) for p in pairs}
    cfg = AveragingConfig(pose_sigma_deg=0.2, pose_sigma_m=0.003)     # well inside the robust loss's scales
    sigma_yaw, sigma_t = noise * np.radians(cfg.pose_sigma_deg), noise * cfg.pose_sigma_m
    poses, covariances = [], []
    for _ in range(draws):
        av = IncrementalAverager(cfg)
        for (a, b), w in weights.items():
            rel = truth[a] @ truth[b].inverse()
            av.add_edge(a, b, Pose4(rel.yaw + rng.normal(0, sigma_yaw / np.sqrt(w)),
                                    np.asarray(rel.t) + rng.normal(0, sigma_t / np.sqrt(w), 3)), w)
        av.update(force_full=True)
        cov = av.covariances()
        covariances.append([cov(k) for k in range(n)])
        poses.append([_params(av.poses[k]) for k in range(n)])
    return np.array(poses), np.array(covariances)


def test_keyframe_covariances_match_the_spread_of_averaged_poses():
    """Relative poses drawn with the noise their weights state; the averaged keyframe poses
    spread (over repeated draws) as their covariances predict, the coupling of heading and
    position included."""
    rng = np.random.default_rng(3)
    pairs = [(i, i + 1) for i in range(7)] + [(0, 4), (2, 6), (1, 7)]
    poses, covariances = _averaged(rng, pairs, 1.0, 300)
    assert np.allclose(covariances[:, 0], 0.0)                         # the anchor holds the map frame
    corr = lambda c: c[0, 1:] / np.sqrt(c[0, 0] * np.diag(c)[1:])       # noqa: E731
    for k in range(1, 8):
        spread, cov = np.cov(poses[:, k].T), covariances[:, k].mean(0)
        ratio = np.sqrt(np.diag(spread) / np.diag(cov))
        assert np.all((ratio > 0.8) & (ratio < 1.25)), (k, ratio)
        assert np.all(np.abs(corr(spread) - corr(cov)) < 0.15), (k, corr(spread), corr(cov))


def test_covariances_grow_where_the_residuals_say_the_measurements_are_noisier_than_stated():
    """Three times the stated noise, on a graph with many loops: the solution's residuals show
    it, and the covariances grow to cover most of the spread."""
    rng = np.random.default_rng(5)
    pairs = [(i, j) for i in range(8) for j in range(i + 1, min(i + 4, 8))]
    poses, covariances = _averaged(rng, pairs, 3.0, 150)
    for k in range(1, 8):
        ratio = np.sqrt(np.diag(np.cov(poses[:, k].T)) / np.diag(covariances[:, k].mean(0)))
        assert np.all((ratio > 0.8) & (ratio < 1.6)), (k, ratio)      # stated noise alone: 3


def test_a_frame_covariance_composes_its_keyframe_and_its_relative_pose():
    rng = np.random.default_rng(4)
    keyframe = Pose4.from_centre(0.7, (1.0, -2.0, 0.3))
    rel = Pose4(0.4, (2.5, 0.5, -0.1))                                   # T_keyframe_frame
    a = rng.normal(size=(4, 4)) * [0.01, 0.05, 0.05, 0.02]
    cov_k = a @ a.T + np.diag([1e-5, 1e-4, 1e-4, 1e-4])
    cov_rel = relative_covariance(2.0, np.radians(1.0), 0.02)
    draws = []
    for _ in range(4000):
        dk, dr = rng.multivariate_normal(np.zeros(4), cov_k), rng.multivariate_normal(np.zeros(4), cov_rel)
        k = Pose4.from_centre(keyframe.yaw + dk[0], _params(keyframe)[1:] + dk[1:])
        draws.append(_params(Pose4(rel.yaw + dr[0], np.asarray(rel.t) + dr[1:]).inverse() @ k))
    draws = np.array(draws)
    mean = _params(rel.inverse() @ keyframe)
    draws[:, 0] = mean[0] + wrap_angle(draws[:, 0] - mean[0])
    cov = frame_covariance(keyframe.yaw, cov_k, rel, cov_rel)
    assert np.allclose(np.cov(draws.T), cov, rtol=0.1, atol=2e-5 * np.sqrt(np.outer(np.diag(cov), np.diag(cov))).max())
    # as a camera pose's covariance: the heading about the map's z is -theta
    ros = ros_pose_covariance(cov, np.radians(1.0)).reshape(6, 6)
    assert np.isclose(ros[5, 5], cov[0, 0]) and np.allclose(ros[:3, 5], -cov[1:, 0])
    assert np.allclose(ros[:3, :3], cov[1:, 1:]) and np.isclose(ros[3, 3], np.radians(1.0) ** 2)


def test_coverage_counts_the_errors_within_their_two_sigma_bound():
    """Errors drawn from the stated covariances lie within the 2-sigma bound about 95% of the
    time (the 4-DoF chi-square quantile); covariances stated four times too small hold far less."""
    from rfm_core.evaluation.trajectory import covariance_coverage

    rng = np.random.default_rng(6)
    truth, estimated, stated, small = {}, {}, {}, {}
    for k in range(2000):
        pose = Pose4.from_centre(rng.uniform(-np.pi, np.pi), rng.uniform(-3, 3, 3)).inverse().matrix()
        a = rng.normal(size=(4, 4)) * [0.02, 0.02, 0.01, 0.01]
        cov4 = a @ a.T + np.diag([1e-4, 1e-4, 1e-4, 1e-5])                # x, y, z, heading
        err = rng.multivariate_normal(np.zeros(4), cov4)
        turn = Pose4(err[3], (0.0, 0.0, 0.0)).matrix()                     # Rz(err[3]): a turn about z
        est = turn @ pose
        est[:3, 3] = pose[:3, 3] + err[:3]
        ros = np.zeros((6, 6))
        ros[np.ix_([0, 1, 2, 5], [0, 1, 2, 5])] = cov4
        truth[k], estimated[k], stated[k], small[k] = pose, est, ros, ros / 16
    right = covariance_coverage(estimated, stated, truth, align=False)
    assert right['frames'] == 2000 and 0.93 < right['within_2sigma'] < 0.97, right
    assert covariance_coverage(estimated, small, truth, align=False)['within_2sigma'] < 0.3
