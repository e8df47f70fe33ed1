"""rfm mapper node: pose averaging, object tracks, relocalization, map persistence (paper 3.5-3.6).

Subscribes rfm/keyframes, rfm/view_graph/edges (transient local: a mapper started after the
matcher gets its kept history; keyframes it already holds are recognised by their view-graph
session and id) and rfm/tracked_frames (from the matcher),
rfm/detections (in localization mode: every frame is localized, as a stream), and in posed mode a pose
source. Publishes rfm/keyframe_poses, rfm/trajectory, rfm/camera_pose and TF (map -> camera)
for every localized frame, rfm/object_map, rfm/object_markers and rfm/status. Services:
rfm/relocalize, rfm/save_map, rfm/load_map, rfm/reset, rfm/set_mode.

Thin rclpy adapter: messages in, rfm_core.session.MapSession calls, messages out.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import rclpy
from geometry_msgs.msg import PoseArray, PoseStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rfm_msgs.msg import FrameDetections, Keyframe, MapperStatus, ObjectMap, TrackedFrame, ViewGraphEdge
from rfm_msgs.srv import LoadMap, Relocalize, SaveMap, SetMode
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from rfm_core.config import MapperNodeConfig
from rfm_core.io.messages import (
    edge_record_from_msg, frame_detections_from_msg, matrix_to_pose, ns_to_stamp, pose_stamped_msg, pose_to_matrix,
    stamp_to_ns, track_map_msgs, tracked_frame_from_msg, transform_stamped_msg, transform_to_matrix,
)
from rfm_core.io.parameters import declare_config
from rfm_core.io.topics import GRAPH_HISTORY
from rfm_core.mapping.map_io import MapFileError
from rfm_core.matching.factory import make_matcher
from rfm_core.session import CameraPose, ExternalPoses, MapSession, SequenceCheck

try:                                               # tf2_ros is optional (pip installs lack it)
    from tf2_ros import TransformBroadcaster
except ImportError:                                # pragma: no cover - depends on the install
    TransformBroadcaster = None

class MapperNode(Node):

    def __init__(self, **kwargs):
        super().__init__('mapper', **kwargs)
        self.config = cfg = declare_config(self, MapperNodeConfig())
        self.map_frame, self.publish_tf, self.tf_child = cfg.map_frame, cfg.publish_tf, cfg.tf_child_frame
        self.map_period, self.map_cpu_share = cfg.map_publish_period_s, cfg.map_max_cpu_share
        self.map_path = cfg.map_path or str(Path(os.environ.get('ROS_HOME', '~/.ros')) / 'rfm' / 'map.rfm')
        self.map_dir = Path(cfg.map_dir or Path(self.map_path).expanduser().parent).expanduser().resolve()
        self.autosave_every = cfg.autosave_every_n_keyframes
        self.autosave_growth = cfg.autosave_growth
        self.pose_source = cfg.pose_source
        config = replace(cfg.mapper, posed=bool(self.pose_source))
        try:
            matcher = make_matcher(cfg.matcher, config.matching, cfg.matcher_weights or None,
                                   on_fallback=lambda msg: self.get_logger().warning(msg))
        except FileNotFoundError as exc:
            raise ValueError(str(exc)) from exc
        self.external_poses = ExternalPoses()
        lookup = {'topic': self.external_poses, 'tf': self._lookup_tf}.get(self.pose_source)
        self.session = MapSession(config, matcher=matcher, pose_lookup=lookup,
                                  idle_full_solve_s=cfg.idle_full_solve_s, warn=self._warn)
        self.session.mode = cfg.mode
        self.mapper = self.session.mapper
        self._map_dirty = False
        self._last_map_time = 0.0
        self._map_seconds = 0.0                  # cost of the last object-map rebuild
        self.num_objects = 0                     # objects in the last published map
        self._sequences: dict = {}               # delivery checks of the matcher's numbered topics

        reliable = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        guard = self._guarded
        kept = QoSProfile(depth=GRAPH_HISTORY, history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(Keyframe, 'rfm/keyframes', guard(self._on_keyframe), kept)
        self.create_subscription(ViewGraphEdge, 'rfm/view_graph/edges', guard(self._on_edge), kept)
        self.create_subscription(TrackedFrame, 'rfm/tracked_frames', guard(self._on_tracked_frame), reliable)
        self.create_subscription(FrameDetections, 'rfm/detections', guard(self._on_detections),
                                 QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
        if self.pose_source == 'topic':
            self.create_subscription(PoseStamped, 'rfm/external_pose', guard(self._on_external_pose), reliable)
        self.tf_buffer = None
        if self.pose_source == 'tf':
            try:
                from tf2_ros import Buffer, TransformListener  # noqa: PLC0415
            except ImportError as exc:
                raise ValueError("pose_source 'tf' needs tf2_ros (a full ROS install); "
                                 "use pose_source 'topic' instead") from exc
            self.tf_buffer = Buffer()
            self.tf_listener = TransformListener(self.tf_buffer, self)
        self.poses_pub = self.create_publisher(PoseArray, 'rfm/keyframe_poses', latched)
        self.path_pub = self.create_publisher(PathMsg, 'rfm/trajectory', latched)
        self.camera_pub = self.create_publisher(PoseStamped, 'rfm/camera_pose', 10)
        self.map_pub = self.create_publisher(ObjectMap, 'rfm/object_map', latched)
        self.marker_pub = self.create_publisher(MarkerArray, 'rfm/object_markers', latched)
        self.status_pub = self.create_publisher(MapperStatus, 'rfm/status', 10)
        self.tf_pub = None
        if self.publish_tf:
            if TransformBroadcaster is not None:
                self.tf_pub = TransformBroadcaster(self)
            else:
                from tf2_msgs.msg import TFMessage  # noqa: PLC0415
                self._tf_raw = self.create_publisher(TFMessage, '/tf', 10)
        self.create_service(Relocalize, 'rfm/relocalize', guard(self._srv_relocalize))
        self.create_service(SaveMap, 'rfm/save_map', guard(self._srv_save))
        self.create_service(LoadMap, 'rfm/load_map', guard(self._srv_load))
        self.create_service(Trigger, 'rfm/reset', guard(self._srv_reset))
        self.create_service(SetMode, 'rfm/set_mode', guard(self._srv_set_mode))
        # wall-clock timers: with use_sim_time a finished bag stops /clock, and the map must
        # still be brought up to date
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(0.1, self._tick, clock=steady)
        self.create_timer(1.0, self._publish_status, clock=steady)
        if cfg.load_map_on_start:
            try:
                header = self._load(self.map_path)
                self.get_logger().info(f'loaded {self.map_path}: {header["keyframes"]} keyframes')
            except MapFileError as exc:
                raise ValueError(f'load_map_on_start: {exc}') from exc
        self.get_logger().info(
            f'mapper ready ({self.session.mode}, {"posed: " + self.pose_source if self.pose_source else "un-posed"}): '
            'rfm/keyframes + rfm/view_graph/edges -> rfm/keyframe_poses, rfm/object_map')

    # ------------------------------------------------------------------ input

    def _warn(self, text: str) -> None:
        self.get_logger().warning(text, throttle_duration_sec=5.0)

    def _guarded(self, callback):
        """``callback`` made safe: an unexpected error is logged (throttled) and the message
        dropped, or the service answers success=false with the error; the node lives on."""
        def run(*args):
            try:
                return callback(*args)
            except Exception as exc:  # noqa: BLE001 - no input may kill the mapper
                self.session.counts['dropped'] += 1
                self.session.message = f'{callback.__name__.lstrip("_")}: unexpected error {exc!r}'
                self.get_logger().error(self.session.message, throttle_duration_sec=5.0)
                if len(args) == 2:                            # a service: (request, response)
                    args[1].success, args[1].message = False, f'internal error: {exc!r}'
                    return args[1]
                return None
        return run

    def _dropped(self, what: str, exc: Exception) -> None:
        self.session.counts['dropped'] += 1
        self._warn(f'{what} dropped: {exc}')

    def _delivered(self, what: str, msg) -> None:
        """Count (and log, throttled) messages the matcher numbered that never arrived."""
        check = self._sequences.setdefault(what, SequenceCheck())
        lost = check.add(int(getattr(msg, 'session', 0)), int(getattr(msg, 'sequence', 0)))
        if lost:
            self.session.message = (f'{lost} {what} from the matcher never arrived ({check.lost} in all): a full '
                                    'queue or a dropped connection; the map has a gap there')
            self._warn(self.session.message)

    @property
    def num_lost(self) -> int:
        return sum(c.lost for c in self._sequences.values())

    def _on_keyframe(self, msg: Keyframe) -> None:
        self._delivered('keyframes', msg)
        try:
            obs = frame_detections_from_msg(msg.detections)
        except ValueError as exc:
            self._dropped(f'keyframe {msg.keyframe_id}', exc)
            return
        self.session.add_keyframe(int(msg.keyframe_id), obs, int(msg.session))

    def _on_edge(self, msg: ViewGraphEdge) -> None:
        self._delivered('edges', msg)
        try:
            edge = edge_record_from_msg(msg)
        except ValueError as exc:
            self._dropped('edge', exc)
            return
        self.session.add_edge(edge, int(msg.session))

    def _on_tracked_frame(self, msg: TrackedFrame) -> None:
        """Mapping mode: log the frame and publish its camera pose (once its keyframe has one)."""
        self._delivered('tracked frames', msg)
        if self.session.mode != 'mapping':
            return
        try:
            track = tracked_frame_from_msg(msg)
        except ValueError as exc:
            self._dropped('tracked frame', exc)
            return
        self._publish_camera(self.session.add_frame(track, int(msg.session)))

    def _on_external_pose(self, msg: PoseStamped) -> None:
        try:
            m = pose_to_matrix(msg.pose)
        except ValueError as exc:
            self._warn(f'external pose dropped: {exc}')
            return
        self.external_poses.add(stamp_to_ns(msg.header.stamp), m)
        self.session.attach_external_poses()

    def _lookup_tf(self, obs):
        """Posed mode (tf): the camera's pose in the map frame at the keyframe's stamp."""
        try:
            tf = self.tf_buffer.lookup_transform(self.map_frame, obs.frame_id,
                                                 rclpy.time.Time(nanoseconds=obs.stamp_ns))
        except Exception:                                  # noqa: BLE001 - not there yet
            return None
        return transform_to_matrix(tf.transform)

    def _on_detections(self, msg: FrameDetections) -> None:
        """Localization mode: localize every frame (as a stream: see
        :mod:`rfm_core.mapping.localization`) and publish the poses found."""
        if self.session.mode != 'localization':
            return
        try:
            obs = frame_detections_from_msg(msg)
        except ValueError as exc:
            self._warn(f'detections dropped: {exc}')
            return
        for camera in self.session.localize(obs):
            self._publish_camera(camera)

    # ------------------------------------------------------------------ output

    def _tick(self) -> None:
        recovered, culled = len(self.mapper.recovered), len(self.mapper.merged)
        changed = self.session.tick()
        for edge in self.mapper.recovered[recovered:]:
            self.get_logger().info(f'tracking recovered: keyframe {edge.target} matched the map through keyframe '
                                   f'{edge.source} ({len(edge.inliers)} objects verified)')
        if len(self.mapper.merged) > culled:                # (culled keyframes are added at the end)
            merged = {k: m.into for k, m in list(self.mapper.merged.items())[culled:]}
            self.get_logger().info(f'culled {len(merged)} redundant keyframe(s) ('
                                   + ', '.join(f'{k} into {a}' for k, a in sorted(merged.items()))
                                   + f'); the map holds {len(self.mapper.keyframes)}, {len(self.mapper.merged)} culled')
        if changed is not False:
            self._map_dirty = True
            self._publish_poses(changed)
            if self.autosave_every and self.session.since_save >= max(
                    self.autosave_every, self.autosave_growth * len(self.mapper.keyframes)):
                self._save(self.map_path, quiet=True)
        wait = max(self.map_period, self._map_seconds / self.map_cpu_share)
        if self._map_dirty and time.monotonic() - self._last_map_time >= wait:
            self._map_dirty = False
            start = time.monotonic()
            self._publish_map()
            self._last_map_time = time.monotonic()
            self._map_seconds = self._last_map_time - start

    def _stamp(self, k: int) -> int:
        return self.mapper.keyframes[k].stamp_ns

    def _publish_poses(self, camera=None) -> None:
        """Keyframe poses and trajectory, and the newest frame's new camera pose."""
        poses = self.mapper.camera_poses()
        if not poses:
            return
        ids = sorted(poses)
        stamp = ns_to_stamp(self._stamp(ids[-1]))
        arr = PoseArray()
        arr.header.stamp, arr.header.frame_id = stamp, self.map_frame
        arr.poses = [matrix_to_pose(poses[k]) for k in ids]
        self.poses_pub.publish(arr)
        path = PathMsg()
        path.header.stamp, path.header.frame_id = stamp, self.map_frame
        path.poses = [pose_stamped_msg(poses[k], self._stamp(k), self.map_frame) for k in ids]
        self.path_pub.publish(path)
        self._publish_camera(camera)

    def _publish_camera(self, camera: CameraPose | None) -> None:
        """rfm/camera_pose and TF of a localized frame (None: nothing new)."""
        if camera is None:
            return
        stamp_ns, frame_id, cam = camera
        self.camera_pub.publish(pose_stamped_msg(cam, stamp_ns, self.map_frame))
        child = self.tf_child or frame_id or 'camera'
        if self.publish_tf:
            tf = transform_stamped_msg(cam, stamp_ns, self.map_frame, child)
            if self.tf_pub is not None:
                self.tf_pub.sendTransform(tf)
            else:
                from tf2_msgs.msg import TFMessage  # noqa: PLC0415
                self._tf_raw.publish(TFMessage(transforms=[tf]))

    def _publish_map(self) -> None:
        tracks = self.mapper.tracks()
        self.num_objects = len(tracks)
        stamp_ns = max((f.stamp_ns for f in self.mapper.keyframes.values()), default=0)
        objects, markers = track_map_msgs(tracks, stamp_ns, self.map_frame, self.mapper.revision)
        self.map_pub.publish(objects)
        self.marker_pub.publish(markers)

    def _publish_status(self) -> None:
        mp = self.mapper
        msg = MapperStatus()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.map_frame
        msg.mode = MapperStatus.MODE_MAPPING if mp.mode == 'mapping' else MapperStatus.MODE_LOCALIZATION
        msg.num_keyframes = len(mp.keyframes)
        msg.num_culled = len(mp.merged)
        msg.num_registered = len(mp.poses)
        active = len(mp.active_edges())
        msg.num_edges = active
        msg.num_edges_rejected = len(mp.measurements()) - active
        msg.num_objects = self.num_objects
        msg.num_components = mp.num_components()
        msg.num_frames = len(mp.frames)
        msg.num_lost = self.num_lost
        msg.last_update_seconds = float(mp.last_update_seconds)
        latency = self.session.relocalize_latency()
        msg.num_relocalize_queries = latency['queries']
        msg.num_relocalized = latency['relocalized']
        msg.relocalize_seconds_median = latency['median_ms'] / 1e3
        msg.relocalize_seconds_p95 = latency['p95_ms'] / 1e3
        msg.message = self.session.message
        self.status_pub.publish(msg)

    # ------------------------------------------------------------------ services

    def _srv_relocalize(self, request, response):
        try:
            obs = frame_detections_from_msg(request.query)
        except ValueError as exc:
            response.success, response.message = False, f'bad query: {exc}'
            return response
        reloc, response.message = self.session.relocalize(obs)
        response.success = reloc is not None
        if reloc is not None:
            response.pose = pose_stamped_msg(reloc.camera_to_map(obs), obs.stamp_ns, self.map_frame)
            response.num_inliers = int(reloc.num_inliers)
            response.keyframe_id = int(reloc.keyframe_id)
        return response

    def _save(self, path: str, quiet: bool = False):
        try:
            written = self.session.save(path or self.map_path)
        except (OSError, ValueError) as exc:
            self.session.message = f'saving the map to {path or self.map_path} failed: {exc}'
            self.get_logger().error(self.session.message, throttle_duration_sec=5.0)
            return None, self.session.message
        text = f'saved {len(self.mapper.keyframes)} keyframes to {written}'
        (self.get_logger().debug if quiet else self.get_logger().info)(text)
        return written, text

    def _request_path(self, path: str) -> str:
        """The file a service request names: map_path when empty, else a path inside map_dir
        (relative ones are taken there); ValueError saying why for one outside it."""
        if not path:
            return self.map_path
        if len(path) > 1024 or '\x00' in path:
            raise ValueError('the path is longer than 1024 characters or holds a NUL')
        p = Path(path).expanduser()
        resolved = (p if p.is_absolute() else self.map_dir / p).resolve()
        if self.map_dir not in resolved.parents:
            raise ValueError(f'{path} is outside map_dir {self.map_dir} (the mapper\'s map_dir parameter sets where '
                             'maps may be saved and loaded)')
        return str(resolved)

    def _srv_save(self, request, response):
        try:
            path = self._request_path(request.path)
        except ValueError as exc:
            response.success, response.message, response.path = False, f'not saved: {exc}', ''
            return response
        written, text = self._save(path)
        response.success = written is not None
        response.message = text
        response.path = str(written or '')
        return response

    def _load(self, path: str) -> dict:
        """Load a map file (MapFileError: the current map is unchanged). The mapper takes the
        configuration the map was built with; settings that differ from this node's
        parameters are logged."""
        header, changed = self.session.load(path)
        if changed:
            text = ', '.join(f'{k}={file} (parameter: {mine})' for k, (file, mine) in changed.items())
            self.get_logger().info(f"{path} was built with other mapper settings; using the map's: {text}")
        self._map_dirty = True
        return header

    def _srv_load(self, request, response):
        try:
            path = self._request_path(request.path)
            header = self._load(path)
        except (MapFileError, ValueError) as exc:
            response.success, response.message = False, f'{exc} (the current map is unchanged)'
            return response
        response.success = True
        response.num_keyframes = len(self.mapper.keyframes)
        response.num_objects = self.num_objects = len(self.mapper.tracks())
        response.message = f'loaded {path}: {header["keyframes"]} keyframes, {response.num_objects} objects'
        self.get_logger().info(response.message)
        self._publish_poses()
        self._publish_map()
        return response

    def _srv_reset(self, request, response):
        self.session.reset()
        self._map_dirty = True
        self.num_objects = 0
        response.success, response.message = True, 'map cleared'
        self.get_logger().info('map cleared')
        return response

    def _srv_set_mode(self, request, response):
        modes = {SetMode.Request.MODE_MAPPING: 'mapping', SetMode.Request.MODE_LOCALIZATION: 'localization'}
        if request.mode not in modes:
            response.success, response.message = False, f'unknown mode {request.mode}: 0 mapping, 1 localization'
            return response
        self.session.mode = modes[request.mode]
        response.success, response.message = True, f'mode: {self.session.mode}'
        self.get_logger().info(response.message)
        return response


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = MapperNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:                 # a bad parameter: say which, exit non-zero
        print(f'mapper: {exc}', file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        if node is not None:
            if node.autosave_every and node.mapper.keyframes and node.session.since_save:
                node._save(node.map_path, quiet=True)
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
