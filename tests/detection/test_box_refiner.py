"""The learned box refiner of depth_clusters (issue #18 item 3)."""
from dataclasses import replace

import numpy as np
import pytest

from rfm_core.detection.box_refiner import BoxRefiner, decode_boxes, encode_target
from rfm_core.detection.labels import NYU40
from rfm_core.detection.depth_clusters import DepthClustersConfig, DepthClustersDetector
from rfm_core.evaluation.detection import DetectionEvaluator
from rfm_core.evaluation.suite import eval_configs
from rfm_core.geometry import iou_3d_paired
from rfm_core.sim.capture import Capture


@pytest.fixture(scope='module')
def realistic_frames():
    """Frames of realistic-world scenes on tuning seeds (never trained on: training is 3000+)."""
    out = []
    for config in eval_configs(4, first_seed=40):
        out += list(Capture(config).frames(np.linspace(0, config.frames - 1, 4).round().astype(int)))
    return out


def test_box_encoding_round_trips_up_to_quarter_turns():
    rng = np.random.default_rng(0)
    boxes = np.c_[rng.normal(size=(200, 3)), rng.uniform(0.1, 2, (200, 3)), rng.uniform(-np.pi, np.pi, 200)]
    targets = np.c_[boxes[:, :3] + rng.normal(0, 0.3, (200, 3)), rng.uniform(0.1, 2, (200, 3)),
                    rng.uniform(-np.pi, np.pi, 200)]
    deltas = np.array([encode_target(b, t) for b, t in zip(boxes, targets)])
    assert np.all(np.abs(np.arctan2(deltas[:, 6], deltas[:, 7])) <= np.pi + 1e-9)
    decoded = decode_boxes(boxes, deltas)
    np.testing.assert_allclose(iou_3d_paired(decoded, targets), 1.0, atol=1e-6)


def test_the_refiner_beats_the_heuristic_boxes_on_unseen_realistic_rooms(realistic_frames):
    """Per-frame AP on furniture made of parts, clutter and both sensor models: the shipped
    weights (scoring and suppressing the fitted boxes, with their predicted full boxes
    attached for the map; its fitted boxes alone; its predicted boxes alone) against the
    heuristic boxes with the calibrated score. Detections are scored by their full boxes."""
    variants = {'heuristic': DepthClustersDetector(DepthClustersConfig(box_refiner='')),
                'default': DepthClustersDetector()}
    assert variants['default'].box_refiner is not None and variants['heuristic'].box_refiner is None
    evaluators = {k: DetectionEvaluator() for k in ('heuristic', 'default', 'fitted', 'refined')}
    counts = dict.fromkeys(evaluators, 0)
    for f in realistic_frames:
        out = {k: det.detect(f.detector_input()) for k, det in variants.items()}
        out['fitted'] = replace(out['default'], full_boxes=None)
        out['refined'] = replace(out['default'], boxes=out['default'].full_boxes, full_boxes=None)
        for k, obs in out.items():
            assert obs.embeddings.shape == (len(obs), out['heuristic'].embeddings.shape[1])
            assert np.all((obs.scores >= 0.25) & (obs.scores <= 1.0)) and np.all(obs.boxes[:, 3:6] > 0)
            evaluators[k].add(obs, f.ground_truth)
            counts[k] += len(obs)
        assert set(out['default'].labels) <= set(NYU40) and all(out['default'].labels)     # named as NYU40's
        # the default publishes the fitted boxes (for relative poses) with the predicted ones attached
        assert out['default'].full_boxes.shape == out['default'].boxes.shape
    h, d, fit, r = (evaluators[k].summary() for k in ('heuristic', 'default', 'fitted', 'refined'))
    assert fit['AP25'] > h['AP25'] and r['AP25'] > h['AP25'] + 0.1 and r['AR25'] > h['AR25'], (h, fit, r)
    assert d['AP25'] > fit['AP25'] + 0.05 and d['AR25'] > fit['AR25'], (fit, d)
    assert counts['default'] < 0.8 * counts['heuristic'], counts     # fewer phantoms and fragments


def test_training_learns_from_simulated_candidates(tmp_path):
    """A short training run on one training-seed scene fits its samples, and the
    checkpoint it writes loads into the detector."""
    import torch

    from rfm_core.training.box_refiner import inference_net, refiner_samples, save, train_box_refiner, training_configs

    (item,) = training_configs([3001], frames_per_scene=4)
    data = refiner_samples(item)
    n = len(data['objectness'])
    assert n > 20 and 0 < data['objectness'].mean() < 1 and data['has_target'].any()
    assert np.all(data['label'][data['has_target']] >= 0)
    net, history = train_box_refiner(data, epochs=60, batch_size=32, lr=1e-2, width=32, log=lambda *_: None)
    assert history[-1][0] < 0.7 * history[0][0] and history[-1][1] < history[0][1], history
    path = tmp_path / 'refiner.npz'
    save(net, path, {'command': 'test'})
    det = DepthClustersDetector(DepthClustersConfig(box_refiner=str(path)))
    assert det.box_refiner.net.width == 32
    # the detector's numpy network is the torch module that was trained
    pts, glob = data['points'][:16].astype(np.float32), data['globals'][:16].astype(np.float32)
    with torch.no_grad():
        trained = net(torch.from_numpy(pts), torch.from_numpy(glob))
    for ours, theirs in zip(det.box_refiner.net(pts, glob), trained):
        np.testing.assert_allclose(ours, theirs.numpy(), atol=1e-4)
    assert inference_net(net).width == 32


def test_missing_or_foreign_weights_say_what_to_do(tmp_path):
    from rfm_core.detection.box_refiner import DEFAULT_BOX_REFINER, parameter_shapes, save_box_refiner

    with pytest.raises(FileNotFoundError, match='train-box-refiner'):
        BoxRefiner.load(tmp_path / 'none.npz')
    save_box_refiner(8, {k: np.zeros(s, np.float32) for k, s in parameter_shapes(8, 3).items()},
                     tmp_path / 'other.npz', {})
    with pytest.raises(ValueError, match='retrain'):
        BoxRefiner.load(tmp_path / 'other.npz')
    shipped = dict(np.load(DEFAULT_BOX_REFINER))
    shipped['head.4.bias'] = shipped['head.4.bias'] * np.nan
    np.savez(tmp_path / 'nan.npz', **shipped)
    with pytest.raises(ValueError, match='head.4.bias is not finite'):
        BoxRefiner.load(tmp_path / 'nan.npz')
