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
