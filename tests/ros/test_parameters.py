"""Each node declares exactly its configuration's settings as ROS parameters, and a value
given at start-up reaches the algorithm it configures."""
import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.parameter import Parameter  # noqa: E402

from rfm_core.config import node_settings  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture()
def ros():
    rclpy.init()
    yield
    rclpy.try_shutdown()


def _declared(node) -> set:
    return {name for name in node._parameters if name not in ('use_sim_time', 'start_type_description_service')}


def test_node_parameters_are_the_configuration_and_reach_the_core(ros):
    from rfm_detector_node.detector_node import DetectorNode
    from rfm_mapper_node.mapper_node import MapperNode
    from rfm_matcher_node.matcher_node import MatcherNode

    matcher = MatcherNode(parameter_overrides=[Parameter('keyframes.min_overlap', value=0.45),
                                               Parameter('matching.inlier_iou', value=0.3)])
    mapper = MapperNode(parameter_overrides=[Parameter('matching.inlier_iou', value=0.3),
                                             Parameter('relocalization.min_inliers', value=3),
                                             Parameter('averaging.window', value=12),
                                             Parameter('autosave_every_n_keyframes', value=0)])
    detector = DetectorNode(parameter_overrides=[Parameter('depth_clusters.stride', value=3),
                                                 Parameter('score_threshold', value=0.4)])
    try:
        for node, name in ((detector, 'detector'), (matcher, 'matcher'), (mapper, 'mapper')):
            assert _declared(node) == {s.name for s in node_settings(name)}
        assert (matcher.graph.config.keyframes.min_overlap, matcher.graph.matching.inlier_iou) == (0.45, 0.3)
        core = mapper.core.mapper.config
        assert (core.matching.inlier_iou, core.relocalization.min_inliers, core.averaging.window) == (0.3, 3, 12)
        assert (detector.detector.config.stride, detector.detector.config.score_threshold) == (3, 0.4)
        described = mapper.describe_parameter('averaging.max_yaw_residual_deg')
        assert 'paper: 3.0' in described.description and described.floating_point_range[0].to_value == 180.0
    finally:
        for node in (detector, matcher, mapper):
            node.destroy_node()


@pytest.mark.parametrize('name, value', [('keyframes.min_overlap', 1.5), ('keyframes.min_detections', 'two'),
                                         ('matcher', 'magic')])
def test_a_bad_parameter_is_refused_by_name(ros, name, value):
    from rfm_matcher_node.matcher_node import MatcherNode

    with pytest.raises(ValueError, match=name):
        MatcherNode(parameter_overrides=[Parameter(name, value=value)])
