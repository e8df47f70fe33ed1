"""One configuration tree: every setting declared once, typed, described, and the README's
parameter tables generated from it."""
from dataclasses import asdict
from pathlib import Path

import pytest

from rfm_core.config import NODES, RfmConfig, node_settings, update_parameter_tables
from rfm_core.mapping.mapper import MapperConfig
from rfm_core.settings import from_dict, settings_of, with_values

README = Path(__file__).resolve().parents[2] / 'README.md'


def test_readme_parameter_tables_are_the_configuration():
    """The README's tables are what `rfm params --readme` generates from rfm_core.config: a
    default or description changed in one place and not the other fails here."""
    text = README.read_text()
    for node in NODES:
        assert f'<!-- parameters: {node} -->' in text
    assert update_parameter_tables(text) == text, 'README parameter tables are stale: rfm params --readme README.md'


def test_every_setting_is_described_once_with_a_valid_default():
    names = []
    for node in NODES:
        settings = node_settings(node)
        assert len({s.name for s in settings}) == len(settings), f'{node}: a parameter declared twice'
        for s in settings:
            assert len(s.description) > 10, f'{node}.{s.name} has no real description'
            assert s.check(s.default) == s.default, f'{node}.{s.name}: default fails its own range/choices'
        names += [f'{node}.{s.name}' for s in settings]
    # the stages every node shares are there, under their section names
    assert {'matcher.matching.inlier_iou', 'mapper.matching.inlier_iou', 'matcher.keyframes.min_overlap',
            'mapper.averaging.window', 'mapper.relocalization.candidates', 'mapper.bundle.max_seconds',
            'detector.depth_clusters.stride', 'detector.cutr.checkpoint'} <= set(names)
    # settings the node sets once for every backend are not repeated per backend
    assert 'detector.depth_clusters.score_threshold' not in names and 'detector.score_threshold' in names


def test_values_are_checked_by_name_and_reach_the_nested_stage():
    cfg = with_values(RfmConfig().matcher, {'keyframes.min_overlap': 0.4, 'matching.inlier_iou': 0.3})
    assert (cfg.graph.keyframes.min_overlap, cfg.matching.inlier_iou) == (0.4, 0.3)
    assert cfg.graph.keyframes.max_yaw_deg == RfmConfig().matcher.graph.keyframes.max_yaw_deg       # others untouched
    mapper = with_values(RfmConfig().mapper, {'averaging.rounds': 5, 'mode': 'localization'})
    assert (mapper.mapper.averaging.rounds, mapper.mode) == (5, 'localization')
    for values, says in (({'keyframes.min_overlaps': 0.4}, 'unknown setting'),
                         ({'keyframes.min_overlap': 1.5}, 'outside'),
                         ({'keyframes.min_detections': 2.5}, 'integer'),
                         ({'keyframes.min_overlap': True}, 'finite number'),
                         ({'matcher': 'magic'}, 'not one of')):
        with pytest.raises(ValueError, match=says):
            with_values(RfmConfig().matcher, values)
    with pytest.raises(ValueError, match='true or false'):
        with_values(RfmConfig().mapper, {'publish_tf': 1})


def test_detector_backend_config_takes_the_common_settings():
    cfg = with_values(RfmConfig().detector, {'backend': 'ground_truth', 'score_threshold': 0.4,
                                             'ground_truth.preset': 'rgb', 'depth_clusters.stride': 4})
    backend = cfg.backend_config()
    assert (type(backend).__name__, backend.score_threshold, backend.preset) == ('GroundTruthConfig', 0.4, 'rgb')


def test_map_file_configuration_round_trips_and_rejects_wrong_types():
    config = with_values(MapperConfig(), {'tracks.merge_affinity': 0.3, 'relocalization.min_inliers': 3,
                                          'bundle_adjustment': True})
    assert from_dict(MapperConfig, asdict(config)) == config
    stored = asdict(config)
    stored['relocalization']['min_inliers'] = 'three'
    with pytest.raises(ValueError, match='finite number'):
        from_dict(MapperConfig, stored)
    assert from_dict(MapperConfig, {'future_stage': {'x': 1}}) == MapperConfig()   # other versions' keys


def test_every_stage_dataclass_field_is_declared():
    """A field added without setting()/section() would be a threshold with no parameter and no
    documentation: settings_of refuses it."""
    assert len(settings_of(RfmConfig())) == sum(len(node_settings(n)) for n in NODES)


def test_parameters_are_few_and_describe_what_they_do():
    """What a user sets, not the history of a value: the three nodes have at most 120
    parameters; each description says what it does in at most 300 characters, with no
    measurements or development history (those belong in docs/design-notes.md)."""
    settings = [s for node in NODES for s in node_settings(node)]
    assert len(settings) <= 120, len(settings)
    for s in settings:
        assert len(s.description) <= 300, (s.name, len(s.description))
        assert not any(word in s.description for word in ('BENCHMARKS', 'session', 'tuning', '%')), s.name
