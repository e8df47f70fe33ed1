"""rfm matcher node: keyframes, a view graph of verified 4-DoF relative poses (paper
3.2-3.4), and every frame's pose relative to a keyframe (tracking).

Subscribes rfm/detections (rfm_msgs/FrameDetections). Publishes rfm/keyframes
(rfm_msgs/Keyframe) and rfm/view_graph/edges (rfm_msgs/ViewGraphEdge), reliable and
transient local with deep queues (rfm_core.io.qos.GRAPH: a mapper that starts or restarts
later still gets them; numbered, so the mapper counts what it missed), and
rfm/tracked_frames (rfm_msgs/TrackedFrame), one per localized frame, and /diagnostics
(frames received, processed, skipped under load, lost; keyframes, edges). An edge's (yaw,
translation) is T_source_target, between the gravity-aligned camera frames of its
keyframes; its inliers pair detection indices of the source and target keyframes.

Thin rclpy wrapper: the algorithms live in rfm_core.matching.
"""
from __future__ import annotations

import random
import time

import rclpy.executors  # (binds rclpy; run_node spins its executor)
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rfm_msgs.msg import FrameDetections, Keyframe, TrackedFrame, ViewGraphEdge

from rfm_core.config import MatcherNodeConfig
from rfm_core.io.entry import run_node
from rfm_core.io.guard import GuardedCallbacks
from rfm_core.io.messages import (diagnostics_msg, edge_msg, frame_detections_from_msg, frame_detections_to_msg,
                                  stamp_to_ns, tracked_frame_to_msg)
from rfm_core.io.parameters import declare_config
from rfm_core.io.qos import GRAPH, RELIABLE, STREAM, qos
from rfm_core.mapping.averaging import AveragingConfig
from rfm_core.mapping.uncertainty import tracked_covariance
from rfm_core.matching.factory import make_matcher
from rfm_core.matching.load import FrameShedder
from rfm_core.matching.view_graph import ViewGraphBuilder


class MatcherNode(GuardedCallbacks, Node):

    def __init__(self, **kwargs):
        super().__init__('matcher', **kwargs)
        self.config = cfg = declare_config(self, MatcherNodeConfig())
        try:
            matcher = make_matcher(cfg.matcher, cfg.matching, cfg.matcher_weights or None,
                                   on_fallback=lambda msg: self.get_logger().warning(msg))
        except FileNotFoundError as exc:
            raise ValueError(str(exc)) from exc
        self.graph = ViewGraphBuilder(cfg.matching, cfg.graph, matcher=matcher)
        self.averaging = AveragingConfig()      # the noise constants of the covariances tracked frames state
        self.keyframe_pub = self.create_publisher(Keyframe, 'rfm/keyframes', qos(GRAPH))
        self.edge_pub = self.create_publisher(ViewGraphEdge, 'rfm/view_graph/edges', qos(GRAPH))
        self.track_pub = self.create_publisher(TrackedFrame, 'rfm/tracked_frames', qos(STREAM))
        # every published keyframe, edge and tracked frame is numbered (the mapper counts gaps)
        self.session_id = random.SystemRandom().randint(1, 2 ** 63 - 1)
        self.sequence = {Keyframe: 0, ViewGraphEdge: 0, TrackedFrame: 0}
        # a deep queue: under load the matcher thins the stream itself (FrameShedder), evenly
        self.shedder = FrameShedder(cfg.shed_after_s, cfg.shed_max_gap_s)
        self.create_subscription(FrameDetections, 'rfm/detections', self._on_detections,
                                 qos(RELIABLE, depth=cfg.queue_depth))
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', qos(RELIABLE))
        self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))          # also while a bag pauses
        self.get_logger().info(f'matcher ready ({cfg.matcher} object matcher): rfm/detections -> rfm/keyframes, '
                               'rfm/view_graph/edges, rfm/tracked_frames')

    def _on_detections(self, msg: FrameDetections, info: dict) -> None:
        """A frame's detections with rclpy's message info (when it was received, the
        publisher's sequence number): skipped under load (FrameShedder), else matched."""
        received = info.get('received_timestamp', 0)
        waited = (time.time_ns() - received) * 1e-9 if received else 0.0
        shedder = self.shedder
        lost, shed = shedder.counts['lost'], shedder.counts['shed']
        admitted = shedder.admit(stamp_to_ns(msg.header.stamp), waited, len(msg.detections),
                                 info.get('publication_sequence_number'))
        if shedder.counts['lost'] > lost:
            self.get_logger().warning(f'{shedder.counts["lost"]} rfm/detections messages lost before the matcher '
                                      f'(its queue of {self.config.queue_depth} overflowed, or the transport dropped '
                                      'them)', throttle_duration_sec=5.0)
        if shedder.counts['shed'] > shed:
            self.get_logger().warning(f'the matcher is {waited:.2f} s behind: skipping frames with depth points only '
                                      f'({shedder.counts["shed"]} of {shedder.counts["received"]} so far; '
                                      'shed_after_s, shed_max_gap_s)', throttle_duration_sec=5.0)
        if not admitted:
            return
        try:
            obs = frame_detections_from_msg(msg)
            keyframe, edges, track = self.graph.add(obs)
        except ValueError as exc:
            self.get_logger().warning(f'detections dropped: {exc}', throttle_duration_sec=5.0)
            return
        if keyframe is not None:                  # this frame or, bridging lost tracking, the previous one
            detections = msg if keyframe.observations is obs else frame_detections_to_msg(keyframe.observations)
            self.keyframe_pub.publish(self._numbered(Keyframe(header=detections.header,
                                                              keyframe_id=keyframe.keyframe_id,
                                                              detections=detections, num_edges=len(edges))))
            self.get_logger().debug(f'keyframe {keyframe.keyframe_id}: {len(edges)} edges')
        for edge in edges:                        # the keyframe's, or those a revisiting frame measured
            self.edge_pub.publish(self._numbered(edge_msg(edge, obs.stamp_ns)))
        if track is not None:            # after its keyframe, so the mapper knows the keyframe
            self.track_pub.publish(self._numbered(tracked_frame_to_msg(
                track, covariance=tracked_covariance(track.num_inliers, track.is_keyframe, self.averaging))))

    def _publish_diagnostics(self) -> None:
        counts = self.shedder.counts
        values = dict(counts, keyframes=self.graph.stats.keyframes, edges=self.sequence[ViewGraphEdge],
                      unexpected_errors=self.unexpected_errors)
        self.diag_pub.publish(diagnostics_msg(
            'rfm matcher', self.config.matcher, bool(counts['lost']),
            f'{counts["processed"]} of {counts["received"]} frames processed', values,
            self.get_clock().now().nanoseconds))

    def _numbered(self, msg):
        self.sequence[type(msg)] += 1
        msg.session, msg.sequence = self.session_id, self.sequence[type(msg)]
        return msg


def main(args=None):
    run_node(rclpy, MatcherNode, 'matcher', args)


if __name__ == '__main__':
    main()
