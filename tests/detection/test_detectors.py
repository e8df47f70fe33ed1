"""Detector backends on rendered frames (seeds disjoint from the evaluation suite)."""
import numpy as np
import pytest

from rfm_core.detection import make_detector
from rfm_core.detection.base import DetectorInput
from rfm_core.detection.depth_clusters import EMBEDDING_DIM
from rfm_core.detection.gravity import GravityFilter
from rfm_core.evaluation.detection import DetectionEvaluator
from rfm_core.sim.capture import Capture, CaptureConfig


@pytest.fixture(scope='module')
def frames():
    out = []
    for seed, style, capture in ((40, 'plain', 'handheld'), (41, 'textured', 'sparse')):
        cap = Capture(CaptureConfig(seed=seed, room_style=style, capture=capture, frames=6, fps=2))
        out += [(cap, f) for f in cap.frames()]
    return out


def inputs(cap, f, gravity=None):
    g = f.ground_truth.gravity_cam if gravity is None else gravity
    return DetectorInput(f.stamp_ns, 'cam', cap.intrinsics, g, f.render.rgb, f.render.depth)


def test_depth_clusters_finds_the_objects(frames):
    det = make_detector('depth_clusters')
    ev = DetectionEvaluator()
    for cap, f in frames:
        obs = det.detect(inputs(cap, f))
        assert obs.embeddings.shape == (len(obs), EMBEDDING_DIM)
        np.testing.assert_allclose(np.linalg.norm(obs.embeddings, axis=1), 1.0, rtol=1e-5)
        assert np.all(obs.scores >= 0.25) and np.all(obs.boxes[:, 3:6] > 0)
        ev.add(obs, f.ground_truth)
    s = ev.summary()
    # a regression guard on 12 frames; the measured accuracy is in BENCHMARKS.md
    assert s['AP15'] > 0.45 and s['AP25'] > 0.3 and s['AR25'] > 0.45, s


def test_depth_clusters_refines_a_tilted_gravity_from_the_floor(frames):
    cap, f = frames[0]
    true_g = f.ground_truth.gravity_cam
    tilt = np.radians(3.0)
    off = np.array([np.sin(tilt), 0.0, 0.0])
    noisy = (true_g + off) / np.linalg.norm(true_g + off)
    obs = make_detector('depth_clusters').detect(inputs(cap, f, noisy))
    err = np.degrees(np.arccos(np.clip(obs.gravity_cam @ true_g, -1, 1)))
    assert err < 0.7                                   # from 3 degrees


def test_depth_clusters_measures_the_walls(frames):
    """The walls it reports lie where the room's walls are (the simulator's room spans
    [0, width] x [0, depth]): normals along the room's axes, distances to the centimetre."""
    from rfm_core.geometry import yaw_matrix
    from rfm_core.mapping.frame_log import pose_from_camera

    det = make_detector('depth_clusters')
    errors = []
    for cap, f in frames:
        obs = det.detect(inputs(cap, f))
        camera = pose_from_camera(f.pose_matrix, obs.gravity_cam, atol=0.2).inverse()     # T_map_aligned
        for nx, ny, d in obs.walls:
            m = yaw_matrix(camera.yaw)[:2, :2] @ [nx, ny]                  # the normal in the room
            axis = int(np.argmax(np.abs(m)))
            assert abs(m[axis]) > np.cos(np.radians(3.0))
            coordinate = np.sign(m[axis]) * (d + m @ np.asarray(camera.t)[:2])   # the wall's x or y
            errors.append(abs(coordinate - (cap.room.size[axis] if m[axis] > 0 else 0.0)))
    assert len(errors) >= 4 and np.median(errors) < 0.02 and max(errors) < 0.1, errors


def test_depth_clusters_handles_empty_and_degenerate_depth(frames):
    cap, f = frames[0]
    det = make_detector('depth_clusters')
    far = np.full_like(f.render.depth, 20.0)            # beyond range: nothing to see
    assert len(det.detect(DetectorInput(0, 'c', cap.intrinsics, [0, 1, 0], f.render.rgb, far))) == 0
    flat = np.full_like(f.render.depth, 2.0)            # a wall filling the view
    assert len(det.detect(DetectorInput(0, 'c', cap.intrinsics, [0, 1, 0], f.render.rgb, flat))) <= 1
    with pytest.raises(ValueError, match='no valid pixels'):
        det.detect(DetectorInput(0, 'c', cap.intrinsics, [0, 1, 0], f.render.rgb,
                                 np.full_like(f.render.depth, np.nan)))


def test_identical_objects_get_similar_embeddings(frames):
    det = make_detector('ground_truth', preset='rgbd', seed=3)
    for cap, f in frames:
        truth = f.ground_truth
        groups = {}
        for oid in truth.object_ids:
            obj = cap.room.objects[oid - 1]
            if obj.group >= 0:
                groups.setdefault(obj.group, []).append(oid)
        pairs = [g for g in groups.values() if len(g) >= 2]
        if pairs:
            obs = det.perturb(truth)
            emb = {oid: e for oid, e in zip(obs.object_ids, obs.embeddings)}
            a, b = pairs[0][:2]
            if a in emb and b in emb:
                others = [e for oid, e in emb.items() if oid not in pairs[0]]
                assert emb[a] @ emb[b] > max((emb[a] @ o for o in others), default=0)
                return
    pytest.fail('no pair of identical visible objects in the test frames')


@pytest.mark.parametrize('preset,ap_min,ap_max', [('perfect', 0.999, 1.0), ('rgbd', 0.7, 0.98),
                                                  ('rgb', 0.2, 0.8)])
def test_ground_truth_presets_degrade_in_order(frames, preset, ap_min, ap_max):
    det = make_detector('ground_truth', preset=preset)
    ev = DetectionEvaluator()
    for _, f in frames:
        obs = det.perturb(f.ground_truth)
        assert obs.backend == f'ground_truth:{preset}'
        assert det.perturb(f.ground_truth).boxes.tolist() == obs.boxes.tolist()  # deterministic
        ev.add(obs, f.ground_truth)
    assert ap_min <= ev.summary()['AP25'] <= ap_max


def test_gravity_filter_uses_the_gyroscope():
    # camera rolling at 1 rad/s about its optical axis, at rest otherwise
    rate, dt = 1.0, 0.005
    lowpass, fused = GravityFilter(tau_s=1.0), GravityFilter(tau_s=1.0)
    for k in range(200):
        t = k * dt
        up = np.array([-np.sin(rate * t), -np.cos(rate * t), 0.0])    # "up" seen by the camera
        force = 9.81 * up
        lowpass.add(int(t * 1e9), force)
        fused.add(int(t * 1e9), force, [0.0, 0.0, rate])
    truth = -up
    err = lambda g: np.degrees(np.arccos(np.clip(g.gravity() @ truth, -1, 1)))  # noqa: E731
    assert err(fused) < 0.5 < 10 < err(lowpass)
    assert not fused.add(int(0.5e9), [0, 0, 0])                        # zero force rejected
    assert not fused.add(int(0.1e9), [0, -9.81, 0])                    # out of order rejected


def test_gravity_at_a_frame_is_gravity_when_it_was_taken():
    """A frame detected after later IMU samples arrived (the detector busy, the IMU queue
    polled) gets gravity as it was at the frame's stamp, not as the camera has turned since."""
    rate, dt = 1.0, 0.005                                   # rolling at 1 rad/s, at rest otherwise
    g = GravityFilter(tau_s=1.0)
    up_at = lambda t: np.array([-np.sin(rate * t), -np.cos(rate * t), 0.0])   # noqa: E731
    for k in range(200):
        g.add(int(k * dt * 1e9), 9.81 * up_at(k * dt), [0.0, 0.0, rate])
    frame_s = 0.8                                           # a frame 0.2 s (11 deg) older than the IMU
    err = lambda down: np.degrees(np.arccos(np.clip(down @ -up_at(frame_s), -1, 1)))  # noqa: E731
    assert err(g.gravity_at(int(frame_s * 1e9))) < 0.5 < 10 < err(g.gravity())
    assert err(g.gravity_at(int(frame_s * 1e9) + 1_000_000)) < 0.5      # within a sample's gap
    np.testing.assert_allclose(g.gravity_at(int(5e9)), g.gravity())        # no sample near: the newest


def test_gravity_filter_starts_from_the_mean_of_its_first_samples():
    """The first sample carries the camera's acceleration at that moment; until tau_s of
    samples have come the estimate is their mean, not the first sample decaying with tau_s."""
    dt, truth = 0.005, np.array([0.0, 1.0, 0.0])           # level camera: down is +y
    g = GravityFilter(tau_s=1.0)
    for k in range(100):                                    # 0.5 s shaken sideways at 2 Hz, 2 m/s^2
        shake = 2.0 * np.cos(2 * np.pi * 2.0 * k * dt)
        g.add(int(k * dt * 1e9), [shake, -9.80665, 0.0])                  # (no gyroscope)
    first = np.degrees(np.arctan2(2.0, 9.80665))            # the first sample's error: 11.5 deg
    assert np.degrees(np.arccos(np.clip(g.gravity() @ truth, -1, 1))) < 0.1 * first


def test_calibrated_score_ranks_boxes_better_than_the_raw_score(frames):
    """The shipped score model (trained on seeds 3000+) raises per-frame AP on these
    frames and keeps exactly the boxes the raw score keeps."""
    from rfm_core.detection.depth_clusters import DepthClustersConfig, DepthClustersDetector

    raw, calibrated = DetectionEvaluator(), DetectionEvaluator()
    raw_det = DepthClustersDetector(DepthClustersConfig(score_model='', box_refiner=''))
    cal_det = DepthClustersDetector(DepthClustersConfig(box_refiner=''))
    for cap, f in frames:
        a, b = raw_det.detect(inputs(cap, f)), cal_det.detect(inputs(cap, f))
        np.testing.assert_allclose(np.sort(a.boxes, axis=0), np.sort(b.boxes, axis=0))
        assert np.all((b.scores >= 0.25) & (b.scores <= 1.0))
        raw.add(a, f.ground_truth)
        calibrated.add(b, f.ground_truth)
    r, c = raw.summary(), calibrated.summary()
    assert c['AP25'] > r['AP25'] and c['AP15'] >= r['AP15'] - 0.01, (r, c)
    assert c['AR25'] == r['AR25']


def test_score_model_fit_and_file_checks(tmp_path):
    from rfm_core.detection.score_model import FEATURES, load_score_model
    from rfm_core.training.depth_score import fit_score_model

    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, len(FEATURES)))
    y = (x[:, 0] - 0.5 * x[:, 1] + 0.3 * rng.normal(size=2000)) > 0
    model = fit_score_model(x, y)
    p = model(x)
    assert np.mean((p > 0.5) == y) > 0.9                 # learns the rule
    assert model.weights[0] > 0 > model.weights[1]
    model.save(tmp_path / 'm.json', {'command': 'test'})
    np.testing.assert_allclose(load_score_model(tmp_path / 'm.json')(x), p, atol=1e-5)
    (tmp_path / 'old.json').write_text('{"features": ["log raw score"], "mean": [0], "std": [1], '
                                       '"weights": [1], "bias": 0}')
    with pytest.raises(ValueError, match='retrain'):
        load_score_model(tmp_path / 'old.json')


def test_an_occluded_bottom_is_recognised():
    """Amodal completion to the floor needs to know when the bottom is hidden: by a nearer
    occluder below the object or by the image border, not by the floor behind it."""
    from rfm_core.detection.depth_clusters import DepthClustersDetector

    det = DepthClustersDetector()
    depth = np.full((120, 160), 3.0, np.float32)             # floor / background
    depth[40:60, 60:100] = 2.0                               # the object
    rows, cols = np.mgrid[40:60:2, 60:100:2]
    pixels = np.stack([rows.ravel(), cols.ravel()], 1)
    assert not det._bottom_hidden(pixels, depth, 2)          # farther things below it
    depth[60:90, 50:110] = 1.2                               # a nearer object in front
    assert det._bottom_hidden(pixels, depth, 2)
    low = np.stack([rows.ravel() + 60, cols.ravel()], 1)    # rows 100-118: cut by the border
    assert det._bottom_hidden(low, np.full((120, 160), 2.0, np.float32), 2)


def test_gravity_filter_takes_an_acceleration_measured_elsewhere_out():
    """A level camera driven straight ahead (no rotation: the gyroscope reads nothing) at
    1 m/s^2 for a second: its accelerometer leans 5.8 deg forward and passes for rest, so the
    filter takes that lean for gravity. Given the acceleration (a robot's odometry), the
    filter keeps gravity level and sees no unseen turn."""
    from rfm_core.detection.gravity import GravityFilter
    up = np.array([0.0, -9.80665, 0.0])           # optical frame, level camera: up is -y, ahead is +z
    ahead = np.array([0.0, 0.0, 1.0])
    errors = {}
    for given in (False, True):
        g = GravityFilter()
        stamp = 0
        for k in range(400):                      # 1 s at rest, then 1 s speeding up
            stamp += 5_000_000
            a = ahead * (1.0 if 200 <= k < 400 else 0.0)
            g.add(stamp, up + a, [0.0, 0.0, 0.0], a if given else None)
        cos = g.gravity() @ np.array([0.0, 1.0, 0.0])
        errors[given] = (np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), g.rest_resets)
    assert errors[False][0] > 5.0 and errors[False][1] == 1     # the drive passed for an unseen tilt
    assert errors[True][0] < 0.01 and errors[True][1] == 0


def test_gravity_filter_follows_a_camera_turned_unseen_and_integrates_the_gyroscope():
    """The gyroscope's integrated orientation follows a turn; a camera turned while the
    gyroscope saw nothing (at rest before and after) gets its gravity from the resting
    accelerometer at once, and its orientation a new epoch."""
    from rfm_core.detection.gravity import GravityFilter
    g = GravityFilter()
    up = np.array([0.0, -9.80665, 0.0])          # optical frame, level camera: up is -y
    stamp = 0
    for _ in range(100):                          # turning about the vertical at 0.5 rad/s
        stamp += 5_000_000
        g.add(stamp, up, [0.0, -0.5, 0.0])
    assert g.epoch == 1
    turned = g.orientation()
    # 99 steps of 5 ms at 0.5 rad/s about the body's -y (up)
    assert np.degrees(np.arccos((np.trace(turned) - 1) / 2)) == pytest.approx(np.degrees(0.5 * 0.495), abs=0.1)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    tilted = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])          # pitched 30 deg, unseen
    for _ in range(40):
        stamp += 5_000_000
        g.add(stamp, tilted @ up, [0.0, 0.0, 0.0])
    assert g.rest_resets == 1 and g.epoch == 2
    assert np.degrees(np.arccos(np.clip(g.gravity() @ (tilted @ -up) / 9.80665, -1, 1))) < 0.5


def test_depth_clusters_measures_the_camera_height_above_the_floor(frames):
    det = make_detector('depth_clusters')
    errors = []
    for cap, f in frames:
        obs = det.detect(inputs(cap, f))
        if np.isfinite(obs.camera_height):
            errors.append(obs.camera_height - f.position[2])     # the simulator's floor is z = 0
    assert len(errors) >= len(frames) - 2                # the floor is in view almost always
    assert np.max(np.abs(errors)) < 0.03, errors         # to a few centimetres: depth noise only
    # a detector that fits no floor measures none
    cap, f = frames[0]
    assert np.isnan(make_detector('ground_truth', preset='rgbd').perturb(f.ground_truth).camera_height)
