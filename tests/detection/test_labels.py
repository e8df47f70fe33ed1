"""Class names: NYU40's, a user's label_map, and the label scores of a map."""
import numpy as np
import pytest

from rfm_core.detection import make_detector
from rfm_core.detection.base import DetectorConfig, DetectorInput
from rfm_core.detection.box_refiner import CLASSES
from rfm_core.detection.labels import NYU40, TO_NYU40, LabelMap, label_map
from rfm_core.evaluation.mapping import evaluate_map, label_scores
from rfm_core.sim.capture import Capture, CaptureConfig


def test_every_detector_class_has_an_nyu40_name_and_nyu40_names_stay():
    assert len(NYU40) == 40 and len(set(NYU40)) == 40
    assert set(CLASSES) == set(TO_NYU40) and set(TO_NYU40.values()) <= set(NYU40)
    names = LabelMap()
    assert [names(c) for c in ('armchair', 'stool', 'monitor', 'tv', 'nightstand', 'wardrobe')] == [
        'chair', 'chair', 'television', 'television', 'night stand', 'cabinet']
    assert all(names(n) == n for n in NYU40) and names('') == ''


def test_a_label_map_renames_a_class_or_a_whole_nyu40_class_and_says_what_is_wrong():
    names = label_map('monitor:monitor, otherprop:clutter')
    assert names.names(['monitor', 'tv', 'vase', 'bin', 'bed']) == ['monitor', 'television', 'clutter', 'clutter',
                                                                   'bed']
    for bad, says in (('monitor', 'FROM:TO'), ('sofa:', 'FROM:TO'), ('spaceship:car', 'neither'),
                      ('tv:a,tv:b', 'twice')):
        with pytest.raises(ValueError, match=says):
            DetectorConfig(label_map=bad)


def test_the_detector_publishes_nyu40_names_and_the_users_renames():
    cap = Capture(CaptureConfig(seed=40, furniture='parts', frames=4, fps=2))
    frames = [DetectorInput(f.stamp_ns, 'cam', cap.intrinsics, f.ground_truth.gravity_cam, f.render.rgb,
                            f.render.depth) for f in cap.frames()]
    plain = [lab for f in frames for lab in make_detector('depth_clusters').detect(f).labels]
    assert plain and set(plain) <= set(NYU40), plain
    renamed = make_detector('depth_clusters', label_map=f'{plain[0]}:renamed')
    out = [lab for f in frames for lab in renamed.detect(f).labels]
    assert out == ['renamed' if lab == plain[0] else lab for lab in plain]


def test_labels_are_scored_on_the_map_objects_that_lie_on_a_real_one():
    truth = np.array([[0, 0, 0.5, 1, 1, 1, 0], [3, 0, 0.5, 1, 1, 1, 0], [0, 3, 0.5, 1, 1, 1, 0]], float)
    boxes = np.array([[0, 0, 0.5, 1, 1, 1, 0],            # on the armchair, called a chair: right (NYU40)
                      [3.05, 0, 0.5, 1, 1, 1, 0],         # on the monitor, called a lamp: wrong
                      [0.05, 3, 0.5, 1, 1, 1, 0],         # on the bed, called a bed: right
                      [6, 6, 0.5, 1, 1, 1, 0]], float)     # nothing real: not scored
    s = label_scores(boxes, ['chair', 'lamp', 'bed', 'bed'], truth, ['armchair', 'monitor', 'bed'])
    assert (s['labelled'], s['right']) == (3, 2)
    assert s['classes'] == {'chair': [1, 1], 'lamp': [1, 0], 'bed': [1, 1]}
    m = evaluate_map(boxes, [1, 1, 1, 1], truth, labels=['chair', 'lamp', 'bed', 'bed'],
                     gt_labels=['armchair', 'monitor', 'bed'])
    assert m['labels'] == s
    assert 'labels' not in evaluate_map(boxes, [1, 1, 1, 1], truth)
