"""rfm matcher node: keyframes, a view graph of verified 4-DoF relative poses (paper
3.2-3.4), and every frame's pose relative to a keyframe (tracking).

Subscribes rfm/detections (rfm_msgs/FrameDetections). Publishes rfm/keyframes
(rfm_msgs/Keyframe) and rfm/view_graph/edges (rfm_msgs/ViewGraphEdge), reliable with deep
queues so the mapper does not miss any, and rfm/tracked_frames (rfm_msgs/TrackedFrame), one
per localized frame. An edge's (yaw, translation) is T_source_target, between the
gravity-aligned camera frames of its keyframes; its inliers pair detection indices of the
source and target keyframes.

Thin rclpy wrapper: the algorithms live in rfm_core.matching.
"""
from __future__ import annotations

import sys

import numpy as np
import rclpy
from geometry_msgs.msg import Vector3
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rfm_msgs.msg import CornerMatch, FrameDetections, Keyframe, ObjectMatch, TrackedFrame, ViewGraphEdge

from rfm_core.io.messages import (
    declare_range_error, frame_detections_from_msg, frame_detections_to_msg, ns_to_stamp, parameter_descriptor,
    tracked_frame_to_msg,
)
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.factory import make_matcher
from rfm_core.matching.view_graph import KeyframeConfig, ViewGraphBuilder


def _float(text, lo, hi):
    return parameter_descriptor(text, lo, hi)


def _int(text, lo, hi):
    return parameter_descriptor(text, lo, hi, integer=True)


class MatcherNode(Node):

    def __init__(self, **kwargs):
        super().__init__('matcher', **kwargs)
        p = self.declare_parameter
        d = MatchingConfig()
        k = KeyframeConfig()
        matching = MatchingConfig(
            match_threshold=p('match_threshold', d.match_threshold, _float(
                'Keep object matches scoring at least this (paper: 0.5)', 0, 1)).value,
            size_ratio_gate=p('size_ratio_gate', d.size_ratio_gate, _float(
                'Classical matcher: minimum size similarity of a match', 0, 1)).value,
            inlier_iou=p('inlier_iou', d.inlier_iou, _float(
                'A match is an inlier when its transferred box has IoU3D >= this (paper: 0.25)', 0, 1)).value,
            min_inlier_ratio=p('min_inlier_ratio', d.min_inlier_ratio, _float(
                'A pose needs this share of all matches as inliers (paper: 0.5)', 0, 1)).value,
            corner_inlier_m=p('corner_inlier_m', d.corner_inlier_m, _float(
                'Corner inlier distance for bundle adjustment (m, paper: 0.10)', 0, 1)).value,
            refine=p('refine_pose', d.refine, parameter_descriptor(
                'Refit the winning pose on all inlier matches (kept if it explains them as well)')).value,
            **declare_range_error(self))
        keyframes = KeyframeConfig(
            min_overlap=p('keyframe_min_overlap', k.min_overlap, _float(
                'New keyframe when fewer than this share of objects match the last one', 0, 1)).value,
            max_translation_m=p('keyframe_max_translation_m', k.max_translation_m, _float(
                'New keyframe after moving this far from the last one (m)', 0, 100)).value,
            max_yaw_deg=p('keyframe_max_yaw_deg', k.max_yaw_deg, _float(
                'New keyframe after turning this much from the last one (deg)', 0, 180)).value,
            min_interval_s=p('keyframe_min_interval_s', k.min_interval_s, _float(
                'No new keyframe sooner than this after the last one (s); 0: off. Fewer keyframes '
                'cost less matching but lower accuracy (see BENCHMARKS.md)', 0, 60)).value,
            max_frame_gap_s=p('max_frame_gap_s', k.max_frame_gap_s, _float(
                'Frames further apart than this are separate views (photos): no motion prior '
                'between them, and their edges need min_retrieved_inliers objects; closer frames '
                'are one stream', 0.01, 3600)).value,
            min_retrieved_inliers=p('min_retrieved_inliers', k.min_retrieved_inliers, _int(
                'Verified objects an edge needs where the motion prior cannot check it (separate '
                'views, retrieved keyframes)', 2, 100)).value,
            min_detections=p('min_detections', k.min_detections, _int(
                'Skip frames with fewer detections', 0, 1000)).value,
            recent_keyframes=p('recent_keyframes', k.recent_keyframes, _int(
                'Match a new keyframe against this many latest keyframes', 0, 100)).value,
            retrieved_keyframes=p('retrieved_keyframes', k.retrieved_keyframes, _int(
                'Plus this many most similar older keyframes (retrieval)', 0, 100)).value,
            unordered_retrieved_keyframes=p('unordered_retrieved_keyframes', k.unordered_retrieved_keyframes, _int(
                'Retrieved keyframes for a keyframe that does not continue a stream (a separate '
                'view: retrieval is what finds the overlaps)', 0, 100)).value,
            motion_prior=p('motion_prior', k.motion_prior, parameter_descriptor(
                'Within a stream (frames at most max_frame_gap_s apart), reject tracking and edges '
                'implying faster motion than max_yaw_rate_deg_s / max_speed_m_s (plus slack). '
                'false: treat every frame as a separate view (stamps mean nothing)')).value,
            max_yaw_rate_deg_s=p('max_yaw_rate_deg_s', k.max_yaw_rate_deg_s, _float(
                'Motion prior: fastest plausible turn (deg/s)', 1, 3600)).value,
            max_speed_m_s=p('max_speed_m_s', k.max_speed_m_s, _float(
                'Motion prior: fastest plausible motion (m/s)', 0.01, 100)).value,
            imu_yaw_tolerance_deg=p('imu_yaw_tolerance_deg', k.imu_yaw_tolerance_deg, _float(
                "Within a stream, a relative pose's yaw may differ from the gyroscope's by this (deg) "
                'plus imu_yaw_drift_deg_s per second between the frames', 0.1, 180)).value,
            imu_yaw_drift_deg_s=p('imu_yaw_drift_deg_s', k.imu_yaw_drift_deg_s, _float(
                "Allowance for the gyroscope's bias (deg/s); raise it for an uncalibrated IMU", 0, 90)).value,
            track_gate_m=p('track_gate_m', k.track_gate_m, _float(
                "Tracking: a box matches the keyframe's box predicted nearest within this (m, the "
                'detector noise) plus the distance the camera can have moved', 0.01, 5)).value,
            max_motion_edge_s=p('max_motion_edge_s', k.max_motion_edge_s, _float(
                'A keyframe that verified nothing, at most this long after the last tracked frame, '
                "is placed by the gyroscope's yaw and the held position (0: never)", 0, 60)).value)
        kind = p('matcher', 'learned', parameter_descriptor(
            "Object matcher: 'learned' (LightGlue-style, shipped weights per detector; falls back to "
            "'classical' for detectors without weights) or 'classical' (embedding similarity + size "
            'gate, Hungarian)', read_only=True)).value
        weights = p('matcher_weights', '', parameter_descriptor(
            "Learned matcher checkpoint (rfm train-matcher); empty: the shipped weights for the frames' "
            'detector', read_only=True)).value
        try:
            matcher = make_matcher(kind, matching, weights or None,
                                   on_fallback=lambda msg: self.get_logger().warning(msg))
        except FileNotFoundError as exc:
            raise ValueError(str(exc)) from exc
        self.graph = ViewGraphBuilder(matching, keyframes, matcher=matcher)
        deep = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                          reliability=ReliabilityPolicy.RELIABLE)
        self.keyframe_pub = self.create_publisher(Keyframe, 'rfm/keyframes', deep)
        self.edge_pub = self.create_publisher(ViewGraphEdge, 'rfm/view_graph/edges', deep)
        self.track_pub = self.create_publisher(TrackedFrame, 'rfm/tracked_frames', deep)
        self.create_subscription(FrameDetections, 'rfm/detections', self._on_detections,
                                 QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.get_logger().info(f'matcher ready ({kind} object matcher): rfm/detections -> rfm/keyframes, '
                               'rfm/view_graph/edges, rfm/tracked_frames')

    def _on_detections(self, msg: FrameDetections) -> None:
        try:
            obs = frame_detections_from_msg(msg)
        except ValueError as exc:
            self.get_logger().warning(f'detections dropped: {exc}', throttle_duration_sec=5.0)
            return
        keyframe, edges, track = self.graph.add(obs)
        if keyframe is not None:                  # this frame or, bridging lost tracking, the previous one
            detections = msg if keyframe.observations is obs else frame_detections_to_msg(keyframe.observations)
            self.keyframe_pub.publish(Keyframe(header=detections.header, keyframe_id=keyframe.keyframe_id,
                                               detections=detections))
            for edge in edges:
                self.edge_pub.publish(self._edge_msg(edge, obs.stamp_ns))
            self.get_logger().debug(f'keyframe {keyframe.keyframe_id}: {len(edges)} edges')
        if track is not None:            # after its keyframe, so the mapper knows the keyframe
            self.track_pub.publish(tracked_frame_to_msg(track))

    @staticmethod
    def _edge_msg(edge, stamp_ns: int) -> ViewGraphEdge:
        rel = edge.relative
        msg = ViewGraphEdge()
        msg.header.stamp = ns_to_stamp(stamp_ns)
        msg.source_id, msg.target_id = edge.source_id, edge.target_id
        msg.yaw = float(rel.pose.yaw)
        t = rel.pose.t
        msg.translation = Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2]))
        msg.num_matches = int(rel.num_matches)
        msg.inliers = [ObjectMatch(source_index=int(s), target_index=int(t_), score=float(sc),
                                   iou=float(iou))
                       for (s, t_), sc, iou in zip(rel.inliers, rel.inlier_scores, rel.inlier_ious)]
        msg.corner_inliers = [CornerMatch(source_index=int(s), source_corner=int(cs),
                                          target_index=int(t_), target_corner=int(ct), error=float(e))
                              for s, cs, t_, ct, e in rel.corner_inliers]
        msg.mean_error = float(rel.mean_error)
        msg.score = float(np.clip(rel.inlier_ratio, 0.0, 1.0))
        return msg


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = MatcherNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:                 # a bad parameter: say which, exit non-zero
        print(f'matcher: {exc}', file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
