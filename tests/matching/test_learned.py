"""The learned (LightGlue-style) object matcher: contract, training, shipped weights."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from rfm_core.evaluation.matching import evaluate_pairs
from rfm_core.matching.classical import ClassicalMatcher
from rfm_core.matching.learned import (
    LearnedMatcher, MatcherNetConfig, batch_inputs, default_weights, load_matcher_net, mutual_matches,
)
from rfm_core.matching.factory import make_matcher
from rfm_core.training.matcher import (
    STRUCTURE_ID_BASE, LabelledFrame, ObjectMatcherNet, TrainConfig, assign_object_ids, batch_tensors,
    inference_net, label_structure, labelled_pairs, match_targets, save, scene_configs, train_matcher,
)
from rfm_core.geometry import Pose4
from rfm_core.observations import FrameObservations


def _frame(n, dim=8, seed=0, backend='test'):
    rng = np.random.default_rng(seed)
    boxes = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(0, 1, n), rng.uniform(0.2, 1, (n, 3)),
                  rng.uniform(-np.pi, np.pi, n)]
    emb = rng.normal(size=(n, dim)).astype(np.float32)
    return FrameObservations(stamp_ns=0, frame_id='cam', intrinsics=None, gravity_cam=np.array([0, 1.0, 0]),
                             boxes=boxes, scores=np.ones(n, np.float32), labels=[''] * n,
                             embeddings=emb / np.linalg.norm(emb, axis=1, keepdims=True),
                             backend=backend)


def test_assignment_contract_and_permutation_equivariance():
    torch.manual_seed(0)
    module = ObjectMatcherNet(MatcherNetConfig(embedding_dim=8, dim=32, layers=2, heads=4)).eval()
    net = inference_net(module)
    a, b = _frame(5, seed=1), _frame(7, seed=2)
    la = net(*batch_inputs([a], [b]))[0]
    perm = np.random.default_rng(3).permutation(7)
    lp = net(*batch_inputs([a], [b.subset(perm)]))[0]
    assert la.shape == (6, 8)
    assert np.all(la <= 1e-6)                                    # log-probabilities
    # the double softmax: each row's match probabilities sum to at most one
    assert np.all(np.exp(la[:-1, :-1]).sum(1) <= 1 + 1e-5)
    # a set model: permuting frame b's detections permutes the columns, nothing else
    np.testing.assert_allclose(lp[:-1, :-1], la[:-1, perm], atol=1e-5)
    np.testing.assert_allclose(lp[:-1, -1], la[:-1, -1], atol=1e-5)
    # padding a batch does not change a pair's result
    batched = net(*batch_inputs([a, _frame(9, seed=4)], [b, _frame(3, seed=5)]))[0]
    np.testing.assert_allclose(batched[:6, :8][:-1, :-1], la[:-1, :-1], atol=1e-5)
    # the numpy network the nodes run is the torch module that was trained, padding included
    with torch.no_grad():
        trained = module(*batch_tensors([a, _frame(9, seed=4)], [b, _frame(3, seed=5)])).numpy()
    np.testing.assert_allclose(batched[:6, :8], trained[0, :6, :8], atol=1e-4)


def test_mutual_matches_need_both_directions_and_the_threshold():
    p = np.array([[0.8, 0.1, 0.05],
                  [0.7, 0.2, 0.05],                 # best is column 0, but column 0 prefers row 0
                  [0.05, 0.1, 0.3]])                # mutual, below 0.5
    la = np.full((4, 4), np.log(1e-3))
    la[:3, :3] = np.log(p)
    rows, cols, probs = mutual_matches(la, 0.5)
    assert rows.tolist() == [0] and cols.tolist() == [0] and probs[0] == pytest.approx(0.8)
    rows, _, _ = mutual_matches(la, 0.25)
    assert rows.tolist() == [0, 2]


def test_weights_round_trip_and_refusals(tmp_path):
    module = ObjectMatcherNet(MatcherNetConfig(embedding_dim=8, dim=32, layers=1))
    path = tmp_path / 'm.npz'
    save(module, path, {'command': 'test'})
    loaded, meta = load_matcher_net(path)
    assert meta == {'command': 'test'}
    a, b = _frame(4, seed=1), _frame(6, seed=2)
    np.testing.assert_allclose(loaded(*batch_inputs([a], [b])), inference_net(module)(*batch_inputs([a], [b])),
                               atol=2e-2)  # fp16
    with pytest.raises(FileNotFoundError, match='rfm train-matcher'):
        load_matcher_net(tmp_path / 'missing.npz')
    (tmp_path / 'junk.npz').write_bytes(b'not a checkpoint')
    with pytest.raises(ValueError, match='cannot be read .* retrain it with .rfm train-matcher'):
        load_matcher_net(tmp_path / 'junk.npz')
    arrays = dict(np.load(path))
    for name, change, reason in (('other', {'__meta__': np.frombuffer(b'{"format": "x", "version": 2}', np.uint8)},
                                  'not an rfm-object-matcher'),
                                 ('nan', {'final.bias': np.full(32, np.nan, np.float16)}, 'not finite'),
                                 ('shape', {'final.bias': np.zeros(31, np.float16)}, 'final.bias has shape'),
                                 ('extra', {'more.weight': np.zeros(3, np.float16)}, 'do not fit'),
                                 ('text', {'final.bias': np.array(['a'] * 32)}, 'not finite floating')):
        np.savez(tmp_path / f'{name}.npz', **(arrays | change))
        with pytest.raises(ValueError, match=reason):
            load_matcher_net(tmp_path / f'{name}.npz')
    # embeddings of the wrong size: a clear error, or the fallback
    matcher = LearnedMatcher(weights=path)
    with pytest.raises(ValueError, match='expects 8-d embeddings'):
        matcher.match(_frame(3, dim=5), _frame(3, dim=5))
    reasons = []
    fallback = LearnedMatcher(weights=path, fallback=ClassicalMatcher(), on_fallback=reasons.append)
    out = fallback.match(_frame(3, dim=5, seed=1), _frame(3, dim=5, seed=1))
    assert len(out) == 3 and len(reasons) == 1
    fallback.match(_frame(3, dim=5, seed=1), _frame(3, dim=5, seed=1))
    assert len(reasons) == 1                                   # reported once


def test_learned_falls_back_for_detectors_without_weights():
    reasons = []
    matcher = make_matcher('learned', on_fallback=reasons.append)
    out = matcher.match(_frame(4, backend='cutr'), _frame(4, backend='cutr'))
    assert len(out) == 4 and 'cutr' in reasons[0]
    with pytest.raises(ValueError, match='learned'):
        make_matcher('magic')


def test_training_labels():
    ids_a, ids_b = np.array([5, -1, 7, 9]), np.array([9, 5, 3])
    matches, un_a, un_b = match_targets(ids_a, ids_b)
    assert matches.tolist() == [[0, 1], [3, 0]] and un_a.tolist() == [1, 2] and un_b.tolist() == [2]
    truth = _frame(3, seed=7)
    truth = replace(truth, object_ids=np.array([11, 12, 13]))
    pred = truth.subset([2, 0])
    pred = replace(pred, boxes=pred.boxes + [0.02, 0, 0, 0, 0, 0, 0])
    far = replace(truth.subset([1]), boxes=truth.boxes[1:2] + [5, 0, 0, 0, 0, 0, 0])
    assert assign_object_ids(pred, truth).tolist() == [13, 11]
    assert assign_object_ids(far, truth).tolist() == [-1]


def test_structure_labels_follow_the_true_poses():
    """Detections that are no object get one id per place in the map: the same fragment
    seen from two poses shares an id, another place gets another, objects keep theirs."""
    fragment = np.array([1.0, 0.2, 2.0, 0.3, 0.4, 0.5, 0.3])            # in the map frame
    elsewhere = fragment + [0, 0, 2.5, 0, 0, 0, 0]
    frames = []
    for pose, boxes, ids in ((Pose4(0.0, (0, 0, 0)), [fragment, elsewhere], [-1, 4]),
                             (Pose4(0.7, (0.4, -0.1, 0.3)), [elsewhere, fragment], [-1, -1])):
        obs = replace(_frame(2, seed=1), boxes=pose.transform_boxes(np.array(boxes)),
                      object_ids=np.array(ids, np.int64))
        frames.append(LabelledFrame(obs, pose, np.array([4])))
    label_structure(frames)
    (a_frag, a_obj), (b_else, b_frag) = (f.observations.object_ids for f in frames)
    assert a_obj == 4 and a_frag == b_frag >= STRUCTURE_ID_BASE
    assert b_else >= STRUCTURE_ID_BASE and b_else != a_frag


@pytest.mark.slow
def test_training_learns_to_match_held_out_pairs():
    """A small network trained for a few seconds beats chance by far on unseen scenes."""
    specs = ['ground_truth:rgb']
    train = labelled_pairs(scene_configs(range(3900, 3904), frames=12), specs, noise_seeds=(0, 1))[specs[0]]
    test = labelled_pairs(scene_configs([3950, 3951], frames=12), specs, noise_seeds=(1,), gaps=(2,))[specs[0]]
    config = MatcherNetConfig(embedding_dim=train[0][0].observations.embeddings.shape[1], dim=64, layers=1)
    torch.manual_seed(0)
    untrained = inference_net(ObjectMatcherNet(config))
    logs = []
    net = train_matcher(train, config, TrainConfig(epochs=10, batch_size=8, learning_rate=3e-3, drop_detections=0.0),
                        log=logs.append)
    first, last = (float(line.split('loss ')[1].split()[0]) for line in (logs[0], logs[-1]))
    assert last < 0.7 * first

    class Fixed(LearnedMatcher):
        def __init__(self, network):
            super().__init__()
            self._fixed = network

    before = evaluate_pairs(test, Fixed(untrained))
    after = evaluate_pairs(test, Fixed(inference_net(net)))
    assert after.f1 > 0.6 and after.f1 > before.f1 + 0.4 and after.match_precision > 0.8, (before, after)


def test_training_drops_detections_of_frames_with_full_boxes():
    """depth_clusters' frames carry full boxes beside the fitted ones (and may carry corner
    descriptors): the augmentation that drops detections drops all of a detection's fields
    (it dropped the boxes and not the full boxes, and rfm train-matcher --backend
    depth_clusters stopped on the first batch)."""
    frames = []
    for seed in (1, 2):
        obs = _frame(6, seed=seed)
        obs = replace(obs, full_boxes=obs.boxes + [0, 0, 0, 0.1, 0.1, 0.1, 0], object_ids=np.arange(1, 7),
                      corner_descriptors=np.ones((6, 8, 4), np.float32))
        frames.append(LabelledFrame(obs, Pose4(0.0, np.zeros(3)), np.arange(1, 7)))
    some = frames[0].observations.subset(np.array([True, False, True, False, False, True]))
    assert np.array_equal(some.object_ids, [1, 3, 6]) and some.full_boxes.shape == (3, 7)
    assert some.corner_descriptors.shape == (3, 8, 4) and np.allclose(some.full_boxes[:, 3:6] - some.boxes[:, 3:6], 0.1)
    config = MatcherNetConfig(embedding_dim=8, dim=32, layers=1)
    net = train_matcher([tuple(frames)] * 4, config, TrainConfig(epochs=2, batch_size=2, drop_detections=0.5))
    assert isinstance(net, ObjectMatcherNet)


@pytest.mark.slow
@pytest.mark.parametrize('spec', ['depth_clusters', 'ground_truth:rgb'])
def test_shipped_weights_beat_the_classical_matcher(spec):
    """The #5 acceptance claim on six held-out scenes (full numbers: rfm eval-matching)."""
    assert default_weights(spec) is not None, 'weights must ship in rfm_core/matching/weights'
    pairs = labelled_pairs(scene_configs(range(2000, 2006), frames=12), [spec], noise_seeds=(2,), gaps=(2,),
                           min_shared=3, visible=True)[spec]
    learned = evaluate_pairs(pairs, LearnedMatcher())
    classical = evaluate_pairs(pairs, ClassicalMatcher())
    assert learned.pairs >= 8
    assert learned.f1 > classical.f1, (learned, classical)
    assert learned.match_precision > 0.8


def test_batched_matching_equals_pair_by_pair():
    """A new keyframe is matched against all its candidates in one padded batch; padding
    must not change any pair's matches."""
    pairs = labelled_pairs(scene_configs(range(2000, 2002), frames=12), ['ground_truth:rgbd'], noise_seeds=(2,),
                           gaps=(1, 2, 3), min_shared=2)['ground_truth:rgbd']
    query = pairs[0][0].observations
    others = [b.observations for _, b in pairs[:6]] + [query.subset([])]     # sizes differ; one empty
    matcher = LearnedMatcher()
    batched = matcher.match_many(query, others)
    assert len(batched) == len(others) and len(batched[-1]) == 0
    assert sum(len(m) for m in batched) > 0
    for b, m in zip(others, batched):
        single = matcher.match(query, b)
        np.testing.assert_array_equal(m.a, single.a)
        np.testing.assert_array_equal(m.b, single.b)
        np.testing.assert_allclose(m.scores, single.scores, atol=1e-4)
    classical = ClassicalMatcher()
    for b, m in zip(others, classical.match_many(query, others)):
        np.testing.assert_array_equal(m.a, classical.match(query, b).a)


def test_the_nodes_run_without_torch():
    """torch costs a node process about 180 MB: the learned matcher and the box refiner run
    in numpy, so neither a node nor its default models import it (only CuTR and training do)."""
    import subprocess
    import sys
    code = ('import sys\n'
            'import numpy as np\n'
            'import rfm_detector_node.detector_node, rfm_matcher_node.matcher_node, rfm_mapper_node.mapper_node\n'
            'from rfm_core.detection.box_refiner import BoxRefiner\n'
            'from rfm_core.matching.factory import make_matcher\n'
            'from rfm_core.matching.learned import default_weights, load_matcher_net\n'
            "net, _ = load_matcher_net(default_weights('depth_clusters'))\n"
            'e = np.ones((1, 3, net.config.embedding_dim), np.float32)\n'
            'p, m = np.zeros((1, 3, 7), np.float32), np.ones((1, 3), bool)\n'
            'assert np.isfinite(net(e, p, m, e, p, m)).all()\n'
            "BoxRefiner.load('default')\n"
            "make_matcher('learned'), make_matcher('classical')\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n")
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
