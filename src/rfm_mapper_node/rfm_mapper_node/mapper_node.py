"""rfm mapper node: pose averaging, object tracks, relocalization, map persistence (paper 3.5-3.6).

Subscribes rfm/keyframes, rfm/view_graph/edges and rfm/tracked_frames (from the matcher),
rfm/detections (in localization mode: every frame is relocalized), and in posed mode a pose
source. Publishes rfm/keyframe_poses, rfm/trajectory, rfm/camera_pose and TF (map -> camera)
for every localized frame, rfm/object_map, rfm/object_markers and rfm/status. Services:
rfm/relocalize, rfm/save_map, rfm/load_map, rfm/reset, rfm/set_mode.

Thin rclpy wrapper: the algorithms live in rfm_core.mapping.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
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

from rfm_core.geometry import Pose4, box_corners
from rfm_core.config import MapperNodeConfig
from rfm_core.io.messages import (
    box_markers_msg, frame_detections_from_msg, matrix_to_pose, ns_to_stamp, object_map_msg, pose_stamped_msg,
    pose_to_matrix, stamp_to_ns, tracked_frame_from_msg, transform_stamped_msg, vector3_to_numpy,
)
from rfm_core.io.parameters import declare_config
from rfm_core.mapping.map_io import MapFileError, load_map, save_map
from rfm_core.mapping.mapper import EdgeRecord, Mapper, camera_to_map
from rfm_core.mapping.tracks import track_colour
from rfm_core.matching.factory import make_matcher
from rfm_core.observations import FrameTrack

try:                                               # tf2_ros is optional (pip installs lack it)
    from tf2_ros import TransformBroadcaster
except ImportError:                                # pragma: no cover - depends on the install
    TransformBroadcaster = None

def _colour(track_id: int) -> tuple:
    """RGBA of a track's markers: its picture colour, lightened."""
    r, g, b = track_colour(track_id)
    return 0.3 + 0.7 * r, 0.3 + 0.7 * g, 0.3 + 0.7 * b, 1.0


def edge_record_from_msg(msg: ViewGraphEdge) -> EdgeRecord:
    """rfm_msgs/ViewGraphEdge -> EdgeRecord; ValueError when malformed."""
    t = vector3_to_numpy(msg.translation)
    if not (np.isfinite(msg.yaw) and np.all(np.isfinite(t))):
        raise ValueError('edge pose is not finite')
    inliers = np.array([[m.source_index, m.target_index] for m in msg.inliers], np.int64).reshape(-1, 2)
    corners = np.array([[c.source_index, c.source_corner, c.target_index, c.target_corner, c.error]
                        for c in msg.corner_inliers], float).reshape(-1, 5)
    return EdgeRecord(int(msg.source_id), int(msg.target_id), Pose4(float(msg.yaw), t), inliers,
                      np.array([m.score for m in msg.inliers], np.float32), corners,
                      float(np.clip(msg.score, 0.0, 1.0)) if np.isfinite(msg.score) else 0.0)


class MapperNode(Node):

    def __init__(self, **kwargs):
        super().__init__('mapper', **kwargs)
        self.config = cfg = declare_config(self, MapperNodeConfig())
        self.map_frame, self.publish_tf, self.tf_child = cfg.map_frame, cfg.publish_tf, cfg.tf_child_frame
        self.idle_full_solve_s = cfg.idle_full_solve_s
        self.map_period, self.map_cpu_share = cfg.map_publish_period_s, cfg.map_max_cpu_share
        self.map_path = cfg.map_path or str(Path(os.environ.get('ROS_HOME', '~/.ros')) / 'rfm' / 'map.rfm')
        self.autosave_every = cfg.autosave_every_n_keyframes
        self.pose_source = cfg.pose_source
        config = replace(cfg.mapper, posed=bool(self.pose_source))
        try:
            matcher = make_matcher(cfg.matcher, config.matching, cfg.matcher_weights or None,
                                   on_fallback=lambda msg: self.get_logger().warning(msg))
        except FileNotFoundError as exc:
            raise ValueError(str(exc)) from exc
        self.mapper = Mapper(config, matcher=matcher)
        self.mapper.mode = mode = cfg.mode

        self.pending_edges: list = []        # edges whose keyframes have not arrived yet
        self.pending_keyframes: list = []    # posed mode: keyframes waiting for a pose
        self.external_poses: list = []       # posed mode (topic): (stamp_ns, frame, 4x4)
        self.counts = dict(keyframes=0, edges=0, frames=0, dropped=0, relocalized=0, relocalize_failed=0)
        self.message = ''
        self._dirty = False
        self._map_dirty = False
        self._full_solve_due = None              # monotonic time of the idle full re-solve
        self._last_map_time = 0.0
        self._map_seconds = 0.0                  # cost of the last object-map rebuild
        self.num_objects = 0                     # objects in the last published map
        self._since_save = 0
        self._camera_frame = ''
        self._last_camera = None             # (stamp_ns, 4x4) of the last pose published
        self._latest_track = None            # the newest tracked frame (published once localized)

        reliable = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(Keyframe, 'rfm/keyframes', self._on_keyframe, reliable)
        self.create_subscription(ViewGraphEdge, 'rfm/view_graph/edges', self._on_edge, reliable)
        self.create_subscription(TrackedFrame, 'rfm/tracked_frames', self._on_tracked_frame, reliable)
        self.create_subscription(FrameDetections, 'rfm/detections', self._on_detections,
                                 QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE))
        if self.pose_source == 'topic':
            self.create_subscription(PoseStamped, 'rfm/external_pose', self._on_external_pose, reliable)
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
        self.create_service(Relocalize, 'rfm/relocalize', self._srv_relocalize)
        self.create_service(SaveMap, 'rfm/save_map', self._srv_save)
        self.create_service(LoadMap, 'rfm/load_map', self._srv_load)
        self.create_service(Trigger, 'rfm/reset', self._srv_reset)
        self.create_service(SetMode, 'rfm/set_mode', self._srv_set_mode)
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
            f'mapper ready ({mode}, {"posed: " + self.pose_source if self.pose_source else "un-posed"}): '
            'rfm/keyframes + rfm/view_graph/edges -> rfm/keyframe_poses, rfm/object_map')

    # ------------------------------------------------------------------ input

    def _on_keyframe(self, msg: Keyframe) -> None:
        try:
            obs = frame_detections_from_msg(msg.detections)
        except ValueError as exc:
            self.counts['dropped'] += 1
            self.get_logger().warning(f'keyframe {msg.keyframe_id} dropped: {exc}', throttle_duration_sec=5.0)
            return
        if self.mapper.mode != 'mapping':
            return
        k = int(msg.keyframe_id)
        self._camera_frame = obs.frame_id or self._camera_frame
        if self.mapper.config.posed:
            self.pending_keyframes.append((k, obs))
            self._attach_external_poses()
            return
        if self.mapper.add_keyframe(k, obs):
            self.counts['keyframes'] += 1
            self._since_save += 1
            self._dirty = True
            self._retry_edges()

    def _on_edge(self, msg: ViewGraphEdge) -> None:
        try:
            edge = edge_record_from_msg(msg)
        except ValueError as exc:
            self.counts['dropped'] += 1
            self.get_logger().warning(f'edge dropped: {exc}', throttle_duration_sec=5.0)
            return
        self._add_edge(edge)

    def _add_edge(self, edge: EdgeRecord) -> None:
        if self.mapper.mode != 'mapping':
            return
        if edge.source not in self.mapper.keyframes or edge.target not in self.mapper.keyframes:
            self.pending_edges.append((time.monotonic(), edge))
            if len(self.pending_edges) > 5000:          # bounded: oldest go first
                self.pending_edges.pop(0)
                self.counts['dropped'] += 1
            return
        try:
            if self.mapper.add_edge(edge):
                self.counts['edges'] += 1
                self._dirty = True
        except ValueError as exc:
            self.counts['dropped'] += 1
            self.get_logger().warning(f'edge dropped: {exc}', throttle_duration_sec=5.0)

    def _retry_edges(self) -> None:
        if not self.pending_edges:
            return
        pending, self.pending_edges = self.pending_edges, []
        now = time.monotonic()
        for stamp, edge in pending:
            if edge.source in self.mapper.keyframes and edge.target in self.mapper.keyframes:
                self._add_edge(edge)
            elif now - stamp < 30.0:
                self.pending_edges.append((stamp, edge))

    def _on_tracked_frame(self, msg: TrackedFrame) -> None:
        """Mapping mode: log the frame and publish its camera pose (once its keyframe has one)."""
        if self.mapper.mode != 'mapping':
            return
        try:
            track = tracked_frame_from_msg(msg)
        except ValueError as exc:
            self.counts['dropped'] += 1
            self.get_logger().warning(f'tracked frame dropped: {exc}', throttle_duration_sec=5.0)
            return
        if not self.mapper.add_frame(track):
            self.counts['dropped'] += 1
            self.get_logger().warning(f'tracked frame dropped: keyframe {track.keyframe_id} has another stamp '
                                      '(did the matcher restart?)', throttle_duration_sec=5.0)
            return
        self.counts['frames'] += 1
        self._latest_track = track
        self._publish_latest_frame()

    def _publish_latest_frame(self) -> None:
        """The newest tracked frame's camera pose, if it has one and is newer than the last
        pose published."""
        track = self._latest_track
        if track is None or (self._last_camera is not None and track.stamp_ns <= self._last_camera[0]):
            return
        cam = self.mapper.frame_pose(track)
        if cam is not None:
            self._camera_frame = track.frame_id or self._camera_frame
            self._publish_camera(track.stamp_ns, track.frame_id, cam)

    def _on_external_pose(self, msg: PoseStamped) -> None:
        try:
            m = pose_to_matrix(msg.pose)
        except ValueError as exc:
            self.get_logger().warning(f'external pose dropped: {exc}', throttle_duration_sec=5.0)
            return
        self.external_poses.append((stamp_to_ns(msg.header.stamp), m))
        self.external_poses = self.external_poses[-2000:]
        self._attach_external_poses()

    def _attach_external_poses(self) -> None:
        """Posed mode: give waiting keyframes the pose with their stamp (within 5 ms)."""
        still = []
        for k, obs in self.pending_keyframes:
            cam = self._lookup_pose(obs)
            if cam is None:
                still.append((k, obs))
                continue
            # camera-to-map -> T_aligned_map of the keyframe (its gravity-aligned frame)
            r = obs.rotation_aligned_from_camera @ cam[:3, :3].T
            t_k_map = np.eye(4)
            t_k_map[:3, :3], t_k_map[:3, 3] = r, -r @ cam[:3, 3]
            try:
                pose = Pose4.from_matrix(t_k_map, atol=0.05)
            except ValueError:
                self.get_logger().warning('external pose disagrees with gravity by > 3 deg; keyframe dropped',
                                          throttle_duration_sec=5.0)
                continue
            if self.mapper.add_keyframe(k, obs):
                self.mapper.set_keyframe_pose(k, pose)
                self.counts['keyframes'] += 1
                self._since_save += 1
                self._dirty = True
        self.pending_keyframes = still[-100:]
        self._retry_edges()

    def _lookup_pose(self, obs):
        if self.pose_source == 'topic':
            best = min(self.external_poses, key=lambda sp: abs(sp[0] - obs.stamp_ns), default=None)
            if best is not None and abs(best[0] - obs.stamp_ns) <= 5_000_000:
                return best[1]
            return None
        try:
            tf = self.tf_buffer.lookup_transform(self.map_frame, obs.frame_id,
                                                 rclpy.time.Time(nanoseconds=obs.stamp_ns))
        except Exception:                                  # noqa: BLE001 - not there yet
            return None
        q, v = tf.transform.rotation, tf.transform.translation
        from rfm_core.geometry import matrix_from_quaternion  # noqa: PLC0415
        m = np.eye(4)
        m[:3, :3] = matrix_from_quaternion([q.x, q.y, q.z, q.w])
        m[:3, 3] = [v.x, v.y, v.z]
        return m

    def _on_detections(self, msg: FrameDetections) -> None:
        """Localization mode: relocalize every frame and publish its pose."""
        if self.mapper.mode != 'localization':
            return
        try:
            obs = frame_detections_from_msg(msg)
        except ValueError as exc:
            self.get_logger().warning(f'detections dropped: {exc}', throttle_duration_sec=5.0)
            return
        reloc = self.mapper.relocalize(obs)
        if reloc is None:
            self.counts['relocalize_failed'] += 1
            return
        self.counts['relocalized'] += 1
        k = reloc.keyframe_id
        self.mapper.frames.add(FrameTrack(obs.stamp_ns, obs.frame_id, obs.gravity_cam, k,
                                          self.mapper.keyframes[k].stamp_ns,
                                          self.mapper.poses[k] @ reloc.pose.inverse(), reloc.num_inliers))
        cam = camera_to_map(reloc.pose, obs)
        self._publish_camera(obs.stamp_ns, obs.frame_id, cam)

    # ------------------------------------------------------------------ output

    def _tick(self) -> None:
        idle_solve = (not self._dirty and self._full_solve_due is not None
                      and time.monotonic() >= self._full_solve_due)
        if self._dirty or idle_solve:
            self._dirty = False
            self._full_solve_due = None
            try:
                stats = self.mapper.update(force_full=idle_solve)
            except Exception as exc:                        # noqa: BLE001 - never die on a solve
                self.message = f'update failed: {exc}'
                self.get_logger().error(self.message, throttle_duration_sec=5.0)
                return
            if stats is not None and stats.kind == 'local' and self.idle_full_solve_s > 0:
                self._full_solve_due = time.monotonic() + self.idle_full_solve_s
            self._map_dirty = True
            self._publish_poses()
            if self.autosave_every and self._since_save >= self.autosave_every:
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

    def _publish_poses(self) -> None:
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
        if self._latest_track is not None:
            self._publish_latest_frame()
        else:                            # no tracked frames (a matcher that does not send them)
            last = ids[-1]
            if self._last_camera is None or self._stamp(last) > self._last_camera[0]:
                self._publish_camera(self._stamp(last), self.mapper.keyframes[last].frame_id, poses[last])

    def _publish_camera(self, stamp_ns: int, frame_id: str, cam) -> None:
        self._last_camera = (stamp_ns, cam)
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
        msg = object_map_msg(np.array([t.box for t in tracks]).reshape(-1, 7), [t.label for t in tracks],
                             [t.track_id for t in tracks], stamp_ns, self.map_frame,
                             scores=[t.score for t in tracks], revision=self.mapper.revision)
        for obj, t in zip(msg.objects, tracks):
            names = sorted(t.class_distribution)
            obj.class_names = names
            obj.class_probabilities = [float(t.class_distribution[n]) for n in names]
            obj.embedding = [float(v) for v in t.embedding]
            obj.observation_keyframe_ids = [int(k) for k in t.observations[:, 0]]
            obj.observation_indices = [int(i) for i in t.observations[:, 1]]
        self.map_pub.publish(msg)
        self.marker_pub.publish(self._markers(tracks, stamp_ns))

    def _markers(self, tracks, stamp_ns: int) -> MarkerArray:
        """The map's tracks, each in its own colour, labelled with class, score and views."""
        boxes = np.array([t.box for t in tracks]).reshape(-1, 7)
        colours = [_colour(t.track_id) for t in tracks]
        return box_markers_msg(
            box_corners(boxes).reshape(-1, 8, 3),
            [f'{t.label or "object"} {t.score:.2f} ({t.num_observations})' for t in tracks],
            boxes[:, :3] + np.c_[np.zeros((len(boxes), 2)), boxes[:, 5] / 2 + 0.08],
            colours, stamp_ns, self.map_frame,
            ids=[int(t.track_id % 2**31) for t in tracks])

    def _publish_status(self) -> None:
        mp = self.mapper
        msg = MapperStatus()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.map_frame
        msg.mode = MapperStatus.MODE_MAPPING if mp.mode == 'mapping' else MapperStatus.MODE_LOCALIZATION
        msg.num_keyframes = len(mp.keyframes)
        msg.num_registered = len(mp.poses)
        active = len(mp.active_edges())
        msg.num_edges = active
        msg.num_edges_rejected = len(mp.edges) - active
        msg.num_objects = self.num_objects
        msg.num_components = mp.num_components()
        msg.num_frames = len(mp.frames)
        msg.last_update_seconds = float(mp.last_update_seconds)
        msg.message = self.message
        self.status_pub.publish(msg)

    # ------------------------------------------------------------------ services

    def _srv_relocalize(self, request, response):
        try:
            obs = frame_detections_from_msg(request.query)
        except ValueError as exc:
            response.success, response.message = False, f'bad query: {exc}'
            return response
        if len(obs) < 2:
            response.success, response.message = False, f'the query has {len(obs)} detections; need >= 2'
            return response
        if not self.mapper.poses:
            response.success, response.message = False, 'the map is empty: nothing to relocalize against'
            return response
        reloc = self.mapper.relocalize(obs)
        if reloc is None:
            self.counts['relocalize_failed'] += 1
            response.success = False
            response.message = 'no keyframe verified a pose for the query (too few matching objects)'
            return response
        self.counts['relocalized'] += 1
        response.success = True
        response.message = (f'relocalized against keyframe {reloc.keyframe_id}: {reloc.num_inliers} inliers, '
                            f'{reloc.agreeing} agreeing keyframes')
        response.pose = pose_stamped_msg(camera_to_map(reloc.pose, obs), obs.stamp_ns, self.map_frame)
        response.num_inliers = int(reloc.num_inliers)
        response.keyframe_id = int(reloc.keyframe_id)
        return response

    def _save(self, path: str, quiet: bool = False):
        try:
            written = save_map(self.mapper, path or self.map_path)
        except (OSError, ValueError) as exc:
            self.message = f'saving the map to {path or self.map_path} failed: {exc}'
            self.get_logger().error(self.message, throttle_duration_sec=5.0)
            return None, self.message
        self._since_save = 0
        text = f'saved {len(self.mapper.keyframes)} keyframes to {written}'
        (self.get_logger().debug if quiet else self.get_logger().info)(text)
        return written, text

    def _srv_save(self, request, response):
        written, text = self._save(request.path)
        response.success = written is not None
        response.message = text
        response.path = str(written or '')
        return response

    def _load(self, path: str) -> dict:
        """Load a map file (MapFileError: the current map is unchanged). The mapper takes the
        configuration the map was built with; settings that differ from this node's
        parameters are logged."""
        before = self.mapper.config
        header = load_map(self.mapper, path)
        if self.mapper.config != before:
            mine, theirs = _flat(before.to_dict()), _flat(self.mapper.config.to_dict())
            changed = ', '.join(f'{k}={theirs[k]} (parameter: {mine.get(k)})'
                                for k in sorted(theirs) if theirs[k] != mine.get(k))
            self.get_logger().info(f'{path} was built with other mapper settings; using the map\'s: {changed}')
        self.pending_edges.clear()
        self._latest_track = self._last_camera = None
        self._dirty = self._map_dirty = True
        self._since_save = 0
        return header

    def _srv_load(self, request, response):
        path = request.path or self.map_path
        try:
            header = self._load(path)
        except MapFileError as exc:
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
        mode = self.mapper.mode
        self.mapper.reset()
        self.mapper.mode = mode
        self.pending_edges.clear()
        self.pending_keyframes.clear()
        self._latest_track = self._last_camera = None
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
        self.mapper.mode = modes[request.mode]
        response.success, response.message = True, f'mode: {self.mapper.mode}'
        self.get_logger().info(response.message)
        return response


def _flat(d: dict, prefix: str = '') -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


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
            if node.autosave_every and node.mapper.keyframes and node._since_save:
                node._save(node.map_path, quiet=True)
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
