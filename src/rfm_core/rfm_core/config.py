"""Every setting of rfm in one tree: :class:`RfmConfig`.

Each stage keeps its frozen dataclass next to its code (``DepthClustersConfig``,
``MatchingConfig``, ``ViewGraphConfig``, ``AveragingConfig``, ``TrackConfig``,
``RelocalizationConfig``, ``BundleConfig``), every field declared with its default,
description, range and the paper's value (:mod:`rfm_core.settings`). This module adds the
nodes' own settings and assembles the tree a node graph runs with:

- ``detector``: :class:`DetectorNodeConfig` (inputs, gravity, and one section per backend);
- ``matcher``: :class:`MatcherNodeConfig` (``matching.*``, ``keyframes.*``, ``motion.*``, ...);
- ``mapper``: :class:`MapperNodeConfig` (outputs, map file, and the mapper's
  ``averaging.*``, ``tracks.*``, ``matching.*``, ``relocalization.*``, ``bundle.*``).

A setting's dotted name is its ROS parameter name on that node
(:func:`rfm_core.io.parameters.declare_config`); the README's parameter tables are generated
from here (``rfm params --readme README.md``) and a test keeps them in step.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace

from rfm_core.detection import BACKENDS
from rfm_core.detection.base import DetectorConfig
from rfm_core.detection.cutr import CutrConfig
from rfm_core.detection.depth_clusters import DepthClustersConfig
from rfm_core.detection.ground_truth import GroundTruthConfig
from rfm_core.mapping.mapper import MODES, MapperConfig
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.view_graph import ViewGraphConfig
from rfm_core.settings import Setting, constant, markdown_table, same_setting, section, setting, settings_of

__all__ = ['DetectorNodeConfig', 'MatcherNodeConfig', 'MapperNodeConfig', 'RfmConfig', 'NODES', 'MATCHERS',
           'node_settings', 'launch_arguments', 'update_parameter_tables']

_COMMON = tuple(s.name for s in settings_of(DetectorConfig))     # set once for every backend
MATCHERS = ('learned', 'classical')


@dataclass(frozen=True)
class DetectorNodeConfig:
    backend: str = setting('depth_clusters', 'Detector: depth_clusters (RGB-D clusters and a small learned box '
                           'refiner), cutr (Cubify Transformer, needs cutr.checkpoint) or ground_truth (the '
                           "simulator's boxes with a noise model, for evaluation)", choices=BACKENDS, read_only=True)
    score_threshold: float = same_setting(DetectorConfig, 'score_threshold')
    max_detections: int = same_setting(DetectorConfig, 'max_detections')
    cloud_voxel_m: float = same_setting(DetectorConfig, 'cloud_voxel_m')
    cloud_max_range_m: float = same_setting(DetectorConfig, 'cloud_max_range_m')
    label_map: str = same_setting(DetectorConfig, 'label_map')
    image_transport: str = setting('raw', "Colour image transport: 'raw' (rgb/image, sensor_msgs/Image) or "
                                   "'compressed' (rgb/image/compressed, JPEG or PNG)", choices=('raw', 'compressed'),
                                   read_only=True)
    every_nth_frame: int = setting(1, 'Process one synchronised frame in n', lo=1, hi=100)
    points_only_backlog: int = setting(8, 'Frames that may wait for the detector (with depth): each taken while '
                                       'another waits is sent with its depth points and no detections, for the '
                                       'matcher to track on its points; a frame arriving when this many wait '
                                       'pushes out the oldest', lo=1, hi=64, read_only=True)
    queue_size: int = setting(10, 'Synchroniser queue per input (messages)', lo=1, hi=100, read_only=True)
    sync_slop_s: float = setting(0.05, 'Largest stamp difference between image, camera_info and depth (s)',
                                 lo=0.0, hi=1.0, read_only=True)
    gravity_source: str = setting('imu', "Gravity from 'imu' (accelerometer and gyroscope, complementary filter) "
                                  "or 'parameter' (the gravity parameter)", choices=('imu', 'parameter'),
                                  read_only=True)
    gravity: list = setting([0.0, 1.0, 0.0], 'Gravity ("down") in the camera optical frame when gravity_source '
                            'is parameter', read_only=True)
    imu_tau_s: float = setting(1.0, 'Gravity filter time constant (s): the gyroscope carries the estimate '
                               'between accelerometer corrections', lo=0.01, hi=10.0, read_only=True)
    odom_frame: str = setting('odom', "A robot's odometry frame: where /tf links it to the camera frame, each "
                              "frame's detections carry the camera's pose in it (the matcher's motion prior); "
                              "'': none", read_only=True)
    odometry_step_s: float = constant(0.05, "On a robot, the camera's acceleration in the odometry frame is the "
                                      'second difference of its positions this far apart (s; /tf interpolates '
                                      'the odometry linearly, so a step below its period sees spikes)', lo=0.005,
                                      hi=0.5)
    odometry_lag_s: float = constant(0.1, "On a robot, an IMU sample takes the camera's acceleration the newest "
                                     'odometry on /tf gives, if that is at most this far from its stamp (s)',
                                     lo=0.0, hi=1.0)
    imu_max_age_s: float = setting(1.0, 'Drop a frame when the last IMU sample is older than it by more than this (s)',
                                   lo=0.01, hi=60.0)
    imu_wait_s: float = setting(0.05, "Wait up to this long for IMU samples up to a frame's stamp (s)",
                                lo=0.0, hi=1.0)
    imu_poll_period_s: float = setting(0.05, 'IMU samples are queued and taken in batches this often and before '
                                       'each frame (s; 0: a callback per sample)', lo=0.0, hi=1.0, read_only=True)
    imu_queue_size: int = setting(200, 'IMU samples held between two batches', lo=1, hi=10000, read_only=True)
    publish_markers: bool = setting(True, 'Publish rfm/detection_markers (boxes with score labels)',
                                    read_only=True)
    diagnostics_period_s: float = setting(1.0, 'Period of /diagnostics (s)', lo=0.1, hi=60.0, read_only=True)
    depth_clusters: DepthClustersConfig = section(DepthClustersConfig, 'the depth_clusters backend',
                                                  exclude=_COMMON)
    ground_truth: GroundTruthConfig = section(GroundTruthConfig, 'the ground_truth backend', exclude=_COMMON)
    cutr: CutrConfig = section(CutrConfig, 'the cutr backend', exclude=_COMMON)

    def backend_config(self) -> DetectorConfig:
        """The selected backend's configuration, with the common settings applied."""
        return replace(getattr(self, self.backend), **{name: getattr(self, name) for name in _COMMON})


@dataclass(frozen=True)
class MatcherNodeConfig:
    matcher: str = setting('learned', "Object matcher: 'learned' (LightGlue-style, shipped weights per detector; "
                           "'classical' for detectors without them) or 'classical' (embedding similarity and a size "
                           'gate, Hungarian)', choices=MATCHERS, read_only=True)
    matcher_weights: str = setting('', "Learned matcher checkpoint (rfm train-matcher); empty: the shipped weights "
                                   "for the frames' detector", read_only=True)
    shed_after_s: float = setting(0.5, 'Under load, once a frame has waited this long, frames with depth points '
                                  'only are skipped where they follow the last frame processed closely: the '
                                  'stream is thinned evenly (s; 0: never skip)', lo=0.0, hi=60.0)
    shed_max_gap_s: float = setting(0.2, '... the longest gap thinning leaves between two frames (s; keep it '
                                    'below motion.max_frame_gap_s)', lo=0.0, hi=60.0)
    queue_depth: int = setting(300, 'rfm/detections messages held for the matcher; beyond it the oldest are lost',
                               lo=1, hi=100000, read_only=True)
    diagnostics_period_s: float = setting(1.0, 'Period of /diagnostics (s)', lo=0.1, hi=60.0, read_only=True)
    matching: MatchingConfig = section(MatchingConfig, 'object matching and verification (paper 3.2-3.4)')
    graph: ViewGraphConfig = section(ViewGraphConfig, 'the view graph: keyframes, motion, tracking, revisits',
                                     inline=True)


@dataclass(frozen=True)
class MapperNodeConfig:
    map_frame: str = setting('map', 'Frame of the map (gravity-aligned, z up)', read_only=True)
    publish_tf: bool = setting(True, "Broadcast the map on /tf above the camera frame's tree: map -> odom_frame "
                               'on a robot whose odometry is on /tf (REP 105), else map -> the root of that tree '
                               '(camera_link of a static mount; the camera frame itself without TF) at frames of '
                               'a stream, not at photos (tf2 would interpolate between them)', read_only=True)
    odom_frame: str = setting('odom', 'The odometry frame: where it is above the camera frame on /tf, the map '
                              'attaches there', read_only=True)
    transform_tolerance_s: float = setting(0.1, 'map -> odom is re-published every tf_publish_period_s, stamped '
                                           'this far ahead (s), so that a lookup at the newest odometry finds it',
                                           lo=0.0, hi=10.0, read_only=True)
    tf_publish_period_s: float = setting(0.05, '... this often (s)', lo=0.005, hi=10.0, read_only=True)
    camera_tf_wait_s: float = setting(2.0, 'Where the camera frame has no /tf yet, wait this long (s, steady clock) '
                                      'from the first camera pose before broadcasting map -> the camera frame '
                                      "itself: a camera mount's latched /tf_static heard late would otherwise give "
                                      'the camera frame a second parent for a while', lo=0.0, hi=60.0,
                                      read_only=True)
    map_publish_period_s: float = setting(1.0, 'Rebuild and publish the object map at most this often (s)',
                                          lo=0.05, hi=60.0)
    map_max_cpu_share: float = setting(0.2, 'Rebuilding the object map may take at most this share of the time',
                                       lo=0.01, hi=1.0)
    idle_full_solve_s: float = setting(1.0, 'Re-solve all poses at once after this long without new keyframes or '
                                       'edges (s; 0: never)', lo=0.0, hi=3600.0)
    map_path: str = setting('', 'Map file of save_map / load_map requests with an empty path, and of autosave; '
                            'empty: $ROS_HOME/rfm/map.rfm (~/.ros/rfm/map.rfm)')
    map_dir: str = setting('', 'Directory that save_map / load_map requests may name files in (relative paths '
                           'are taken inside it, paths outside it refused); empty: the directory of map_path',
                           read_only=True)
    autosave_every_n_keyframes: int = setting(10, 'Save the map to map_path every n new keyframes (0: never) ...',
                                              lo=0, hi=100000)
    autosave_growth: float = setting(0.1, '... or, for a larger map, once it has grown by this fraction since the '
                                     'last save', lo=0.0, hi=10.0)
    autosave_period_s: float = setting(60.0, '... or, in mapping mode, this long after the last save with frames '
                                       'localized since (s; 0: only with new keyframes)', lo=0.0, hi=86400.0)
    load_map_on_start: bool = setting(False, 'Load map_path at start-up', read_only=True)
    mode: str = setting('mapping', "Start in 'mapping' or 'localization' mode (the map frozen, every frame "
                        'localized against it); rfm/set_mode switches', choices=MODES, read_only=True)
    pose_source: str = setting('', "Posed mode: '' (un-posed: pose averaging), 'topic' (rfm/external_pose, the "
                               "camera's PoseStamped in the map frame) or 'tf' (map_frame -> camera frame)",
                               choices=('', 'topic', 'tf'), read_only=True)
    matcher: str = setting('learned', "Relocalization's object matcher: 'learned' or 'classical'",
                           choices=MATCHERS, read_only=True)
    matcher_weights: str = setting('', "Relocalization's learned matcher checkpoint; empty: shipped",
                                   read_only=True)
    mapper: MapperConfig = section(MapperConfig, 'the mapper (averaging, tracks, relocalization, bundle '
                                   'adjustment)', inline=True)


@dataclass(frozen=True)
class RfmConfig:
    detector: DetectorNodeConfig = section(DetectorNodeConfig, 'rfm_detector_node')
    matcher: MatcherNodeConfig = section(MatcherNodeConfig, 'rfm_matcher_node')
    mapper: MapperNodeConfig = section(MapperNodeConfig, 'rfm_mapper_node')


NODES = ('detector', 'matcher', 'mapper')


def node_settings(node: str) -> list[Setting]:
    """The ROS parameters of one node of the graph (``detector``, ``matcher``, ``mapper``)."""
    if node not in NODES:
        raise ValueError(f'unknown node {node!r}; one of {", ".join(NODES)}')
    return settings_of(getattr(RfmConfig(), node))


#: rfm.launch.py's arguments that set node parameters: argument -> (node.parameter, ...)
LAUNCH_PARAMETERS = {
    'backend': ('detector.backend',),
    'cutr_checkpoint': ('detector.cutr.checkpoint',),
    'matcher': ('matcher.matcher', 'mapper.matcher'),
    'map_path': ('mapper.map_path',),
    'mode': ('mapper.mode',),
    'load_map_on_start': ('mapper.load_map_on_start',),
}


def launch_arguments() -> list:
    """[(argument, default as launch text, description, [(node, parameter)], is text)] of the
    launch file's arguments that set node parameters, defaults and descriptions from the
    settings (``is text``: a string parameter, which launch must not parse as YAML)."""
    out = []
    for name, targets in LAUNCH_PARAMETERS.items():
        pairs = [tuple(t.split('.', 1)) for t in targets]
        node, param = pairs[0]
        s = next(s for s in node_settings(node) if s.name == param)
        default = str(s.default).lower() if isinstance(s.default, bool) else str(s.default)
        text = s.description + (f' (one of: {", ".join(s.choices)})' if s.choices else '')
        out.append((name, default, text, pairs, s.kind == 'str'))
    return out


_TABLE = re.compile(r'(<!-- parameters: (\w+) -->\n).*?(<!-- end parameters -->)', re.S)


def update_parameter_tables(text: str) -> str:
    """``text`` (the README) with every block between ``<!-- parameters: NODE -->`` and
    ``<!-- end parameters -->`` replaced by that node's parameter table."""
    return _TABLE.sub(lambda m: m.group(1) + markdown_table(node_settings(m.group(2))) + m.group(3), text)
