"""rfm mapper node: pose averaging, object tracks, relocalization, map files (paper 3.5-3.6).

Subscribes rfm/keyframes, rfm/view_graph/edges (their kept history too), rfm/tracked_frames,
rfm/detections (localization mode), /tf, /tf_static, in posed mode rfm/external_pose. Publishes
rfm/keyframe_poses, rfm/trajectory, rfm/camera_pose, TF (map -> the root of the camera's tree:
odom on a robot), rfm/object_map, rfm/object_markers, rfm/status. Services: rfm/relocalize, rfm/save_map, rfm/load_map,
rfm/reset, rfm/set_mode. Messages in, rfm_core.mapper_core.MapperCore, messages out.
"""
from __future__ import annotations

import rclpy.executors  # (binds rclpy; run_node spins its executor)
from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Path
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rfm_msgs.msg import FrameDetections, Keyframe, MapperStatus, ObjectMap, TrackedFrame, ViewGraphEdge
from rfm_msgs.srv import LoadMap, Relocalize, SaveMap, SetMode
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from rfm_core.config import MapperNodeConfig
from rfm_core.io import messages as m
from rfm_core.io.entry import run_node
from rfm_core.io.guard import GuardedCallbacks, decoded
from rfm_core.io.parameters import declare_config
from rfm_core.io.qos import GRAPH, LATCHED, RELIABLE, STREAM, TF, qos
from rfm_core.mapper_core import MapperCore


class MapperNode(GuardedCallbacks, Node):

    def __init__(self, **kwargs):
        super().__init__('mapper', **kwargs)
        self.config = cfg = declare_config(self, MapperNodeConfig())
        self.core = core = MapperCore(cfg, warn=lambda text: self.get_logger().warning(text, throttle_duration_sec=5.0))
        inputs = [(Keyframe, 'rfm/keyframes', self._on_keyframe, GRAPH),
                  (ViewGraphEdge, 'rfm/view_graph/edges', self._on_edge, GRAPH),
                  (TrackedFrame, 'rfm/tracked_frames', self._on_tracked_frame, STREAM),
                  (FrameDetections, 'rfm/detections', self._on_detections, RELIABLE)]
        if cfg.pose_source == 'topic':
            inputs.append((PoseStamped, 'rfm/external_pose', self._on_external_pose, STREAM))
        if cfg.publish_tf or cfg.pose_source == 'tf':
            inputs += [(TFMessage, '/tf', self._on_tf, TF),
                       (TFMessage, '/tf_static', lambda msg: self._on_tf(msg, static=True), LATCHED)]
        for kind, topic, callback, profile in inputs:
            self.create_subscription(kind, topic, callback, qos(profile))
        self.pub = {topic: self.create_publisher(kind, topic, qos(profile)) for kind, topic, profile in (
            (PoseArray, 'rfm/keyframe_poses', LATCHED), (Path, 'rfm/trajectory', LATCHED),
            (ObjectMap, 'rfm/object_map', LATCHED), (MarkerArray, 'rfm/object_markers', LATCHED),
            (PoseWithCovarianceStamped, 'rfm/camera_pose', RELIABLE), (MapperStatus, 'rfm/status', RELIABLE))}
        if cfg.publish_tf:
            self.pub['/tf'] = self.create_publisher(TFMessage, '/tf', qos(TF))
        for kind, name, answer in ((Relocalize, 'relocalize',
                                    lambda q: m.relocalize_answer(q.query, core.relocalize, cfg.map_frame)),
                                   (SaveMap, 'save_map', lambda q: core.save(q.path)),
                                   (LoadMap, 'load_map', lambda q: core.load(q.path)),
                                   (Trigger, 'reset', lambda q: core.reset()),
                                   (SetMode, 'set_mode', lambda q: core.set_mode(q.mode))):
            self.create_service(kind, f'rfm/{name}', self._service(name, answer))
        steady = Clock(clock_type=ClockType.STEADY_TIME)       # a finished bag stops sim time; the map goes on
        self.create_timer(0.1, self._tick, clock=steady)
        self.create_timer(1.0, self._publish_status, clock=steady)
        if cfg.publish_tf:                          # map -> odom held between frames (the node's clock: sim time too)
            self.create_timer(cfg.tf_publish_period_s, self._republish_tf)
        self.get_logger().info(f'mapper ready ({cfg.mode}, {cfg.pose_source or "un-posed"})')

    def callback_failed(self, name: str, exc: Exception) -> None:
        super().callback_failed(name, exc)
        self.core.failed(name, exc)                  # rfm/status says it

    def _on_keyframe(self, msg) -> None:
        obs = decoded(m.frame_detections_from_msg, msg.detections, f'keyframe {msg.keyframe_id}', self.core.dropped)
        self.core.keyframe(int(msg.keyframe_id), obs, msg.session, msg.sequence, edges=int(msg.num_edges))

    def _on_edge(self, msg) -> None:
        self.core.edge(decoded(m.edge_record_from_msg, msg, 'edge', self.core.dropped), msg.session, msg.sequence)

    def _on_tracked_frame(self, msg) -> None:
        track = decoded(m.tracked_frame_from_msg, msg, 'tracked frame', self.core.dropped)
        self._publish_camera(self.core.tracked_frame(track, msg.session, msg.sequence))

    def _on_external_pose(self, msg) -> None:
        pose = decoded(lambda p: m.pose_to_matrix(p.pose), msg, 'external pose', self.core.dropped)
        self.core.external_pose(m.stamp_to_ns(msg.header.stamp), pose)

    def _on_detections(self, msg) -> None:
        if self.core.session.mode == 'localization':
            for camera in self.core.detections(decoded(m.frame_detections_from_msg, msg, 'detections',
                                                       self.core.dropped)):
                self._publish_camera(camera)

    def _on_tf(self, msg, static: bool = False) -> None:
        for link in decoded(m.transforms_from_msg, msg, '/tf message', self.core.dropped) or ():
            self.core.transform(*link, static)

    def _republish_tf(self) -> None:
        held = self.core.held_transform(self.get_clock().now().nanoseconds)
        if held is not None:
            self._publish([('/tf', m.attachment_msg(*held, self.config.map_frame))])

    def _tick(self) -> None:
        tick = self.core.tick()
        for line in tick.log:
            self.get_logger().info(line)
        for camera in tick.earlier:                 # frames held until their keyframe's edges were in
            self._publish_camera(camera)
        self._publish(m.tick_outputs(tick, self.config.map_frame, self.core.attach(tick.camera)))

    def _publish_camera(self, camera) -> None:
        self._publish(m.camera_pose_outputs(camera, self.config.map_frame, self.core.attach(camera)))

    def _publish_status(self) -> None:
        self._publish([('rfm/status', m.mapper_status_msg(self.core.status(), self.get_clock().now().nanoseconds,
                                                          self.config.map_frame))])

    def _publish(self, outputs) -> None:
        for topic, msg in outputs:
            if topic in self.pub:                   # (/tf with publish_tf only)
                self.pub[topic].publish(msg)

    def _service(self, name: str, answer):
        """A service callback: the response's fields from ``answer(request)``, logged."""
        def callback(request, response):
            for field, value in answer(request).items():
                setattr(response, field, value)
            if name != 'relocalize':
                self.get_logger().info(response.message)
            return response
        callback.__name__ = name
        return callback


def main(args=None):
    run_node(rclpy, MapperNode, 'mapper', args, close=lambda node: node.core.close())


if __name__ == '__main__':
    main()
