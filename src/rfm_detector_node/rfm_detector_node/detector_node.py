"""rfm detector node: per-frame metric 3D boxes and embeddings (paper section 3.1).

Subscribes (all remappable; sensor-data QoS, so reliable and best-effort publishers connect):
  rgb/image (sensor_msgs/Image: rgb8, bgr8, mono8; or with image_transport:=compressed,
  rgb/image/compressed: sensor_msgs/CompressedImage, JPEG or PNG), rgb/camera_info, depth/image (16UC1 mm
  or 32FC1 m, registered to rgb; when the backend needs depth), imu (sensor_msgs/Imu, for
  gravity and the gyroscope; queued and taken in batches, see imu_poll_period_s),
  ground_truth/detections (rfm_msgs/FrameDetections; backend ground_truth only).
Publishes:
  rfm/detections (rfm_msgs/FrameDetections), rfm/detection_markers (MarkerArray),
  /diagnostics (diagnostic_msgs/DiagnosticArray: counters, latency).

Frames are processed by one worker thread. With depth, up to points_only_backlog frames may
wait: a frame taken while the next one already waits is sent with its depth points and no
detections (a few ms; the matcher tracks it on the points), the frame it catches up on is
detected in full, and a frame arriving while the backlog is full pushes out the oldest
waiting (counted as dropped). Without, a frame arriving while the worker is busy replaces
the waiting one (newest wins). Nothing queues without bound.
Thin rclpy adapter: frames through rfm_core.detection.frontend, detections out.
"""
from __future__ import annotations

import threading
import time

import rclpy.executors  # (binds rclpy; run_node spins its executor)
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rfm_msgs.msg import FrameDetections
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from rfm_core.config import DetectorNodeConfig
from rfm_core.detection import make_detector
from rfm_core.detection.frontend import DetectorFrontend, FrameWorker
from rfm_core.io.entry import run_node
from rfm_core.io.guard import GuardedCallbacks
from rfm_core.io.messages import detection_markers_msg, diagnostics_msg, frame_detections_to_msg, transforms_from_msg
from rfm_core.io.parameters import declare_config
from rfm_core.io.qos import LATCHED, RELIABLE, SENSOR, TF, qos
from rfm_core.matching.config import MONOCULAR_RANGE_ERROR
from rfm_detector_node.polling import PolledGroup, take_all


class DetectorNode(GuardedCallbacks, Node):

    def __init__(self, **kwargs):
        super().__init__('detector', **kwargs)
        self.config = cfg = declare_config(self, DetectorNodeConfig())
        self.backend, self.image_transport, self.gravity_source = cfg.backend, cfg.image_transport, cfg.gravity_source
        self.publish_markers, self.diagnostics_period = cfg.publish_markers, cfg.diagnostics_period_s
        self.detector = make_detector(self.backend, cfg.backend_config())
        if self.detector.monocular:
            error, per_m = MONOCULAR_RANGE_ERROR
            self.get_logger().info(
                f'{self.backend} judges distance from RGB alone: give the matcher and mapper '
                f'matching.range_error:={error} matching.range_error_per_m:={per_m} (rfm run does for '
                'ground_truth rgb)')
        self.frontend = DetectorFrontend(
            self.detector, self._submit, fixed_gravity=cfg.gravity if cfg.gravity_source == 'parameter' else None,
            sync_slop_s=cfg.sync_slop_s, queue_size=cfg.queue_size, every_nth_frame=cfg.every_nth_frame,
            warn=self._warn, poll_imu=self._take_imu, **{name: getattr(cfg, name) for name in (
                'imu_tau_s', 'imu_max_age_s', 'imu_wait_s', 'odom_frame', 'odometry_step_s', 'odometry_lag_s')})
        self.imu_sub = None
        self._imu_lock = threading.Lock()
        self.counts = self.frontend.counts
        self.last_latency_ms = float('nan')
        self.last_detections = 0

        self.pub = self.create_publisher(FrameDetections, 'rfm/detections', qos(RELIABLE))
        self.marker_pub = (self.create_publisher(MarkerArray, 'rfm/detection_markers', qos(RELIABLE))
                           if self.publish_markers else None)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', qos(RELIABLE))
        sensor = qos(SENSOR)
        add = self.frontend.add_image
        if self.backend == 'ground_truth':
            self.create_subscription(FrameDetections, 'ground_truth/detections', self.frontend.add_ground_truth,
                                     qos(RELIABLE, depth=50))
            inputs = 'ground_truth/detections'
        else:
            colour = 'rgb/image/compressed' if self.image_transport == 'compressed' else 'rgb/image'
            self.create_subscription(CompressedImage if self.image_transport == 'compressed' else Image, colour,
                                     lambda m: add(0, m), sensor)
            self.create_subscription(CameraInfo, 'rgb/camera_info', lambda m: add(1, m), sensor)
            if self.detector.needs_depth:
                self.create_subscription(Image, 'depth/image', lambda m: add(2, m), sensor)
            inputs = f'{colour}, rgb/camera_info' + (', depth/image' if self.detector.needs_depth else '')
        if self.gravity_source == 'imu' or self.backend == 'ground_truth':
            # gravity (unless given or simulated) and the gyroscope's orientation, taken in
            # batches (every imu_poll_period_s and before each frame), not a callback per sample
            if cfg.imu_poll_period_s > 0:
                self.imu_sub = self.create_subscription(Imu, 'imu', self._on_imu, qos(SENSOR, depth=cfg.imu_queue_size),
                                                        callback_group=PolledGroup())
                self.create_timer(cfg.imu_poll_period_s, self._take_imu,
                                  clock=Clock(clock_type=ClockType.STEADY_TIME))   # also while a bag pauses
            else:
                self.create_subscription(Imu, 'imu', self._on_imu, sensor)
            inputs += ', imu' if self.backend != 'ground_truth' else ', imu (optional)'
        if cfg.odom_frame:                         # a robot's odometry: the camera's pose in it, per frame
            self.create_subscription(TFMessage, '/tf', lambda msg: self._on_tf(msg, False), qos(TF))
            self.create_subscription(TFMessage, '/tf_static', lambda msg: self._on_tf(msg, True), qos(LATCHED))
        self.create_timer(self.diagnostics_period, self._publish_diagnostics,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))          # also while a bag pauses
        self.points_only = self.detector.needs_depth and cfg.cloud_voxel_m > 0
        self.worker = FrameWorker(self._work, lambda *job: self._work(*job, pushed_out=True), name='detector_worker',
                                  backlog=cfg.points_only_backlog if self.points_only else 1)
        self.get_logger().info(f'detector ready: backend={self.backend}, inputs: {inputs}')

    def _take_imu(self) -> None:
        """The IMU samples queued since the last call into the gravity filter (from the
        timer and from the worker before it detects a frame)."""
        if self.imu_sub is not None:
            with self._imu_lock:
                take_all(self.imu_sub, self._on_imu)

    def _on_tf(self, msg, static: bool) -> None:
        try:
            links = transforms_from_msg(msg)
        except (ValueError, AttributeError) as exc:
            self._warn(f'/tf message dropped: {exc}')
            return
        for link in links:
            self.frontend.add_transform(*link, static)

    def _on_imu(self, msg) -> None:
        try:
            self.frontend.add_imu(msg)
        except Exception as exc:  # noqa: BLE001 - a malformed sample never stops the batch
            self._warn(f'IMU sample dropped: {exc!r}')

    def _warn(self, text: str) -> None:
        self.get_logger().warning(text, throttle_duration_sec=5.0)

    def _submit(self, kind, payload) -> None:
        if self.worker.submit(kind, payload):
            self.counts['dropped_busy'] += 1

    def _work(self, kind, payload, pushed_out: bool = False) -> None:
        """One frame on the worker thread: detect it (its depth points only when the next one
        waits; one pushed out of the backlog: its odometry alone, on a robot), publish."""
        start = time.perf_counter()
        points_only = self.points_only and self.worker.waiting > 0
        try:
            obs = (self.frontend.odometry_only(kind, payload) if pushed_out
                   else self.frontend.detect(kind, payload, points_only))
        except (ValueError, RuntimeError) as exc:
            self.counts['dropped_invalid'] += 1
            self._warn(f'frame dropped: {exc}')
            return
        except Exception as exc:  # noqa: BLE001 - never let a bad frame kill the node
            self.counts['dropped_invalid'] += 1
            self.get_logger().error(f'frame dropped, unexpected error: {exc!r}', throttle_duration_sec=5.0)
            return
        if obs is None:
            return
        full = not (points_only or pushed_out)
        self.counts['processed'] += not pushed_out
        if full:
            self.last_latency_ms = 1e3 * (time.perf_counter() - start)
            self.last_detections = len(obs)
        try:
            self.pub.publish(frame_detections_to_msg(obs))
            self.counts['published'] += 1
            if self.marker_pub is not None and full:
                self.marker_pub.publish(detection_markers_msg(obs))
        except Exception as exc:  # noqa: BLE001 - e.g. publishing during shutdown
            self.get_logger().debug(f'publish failed: {exc!r}')

    def _publish_diagnostics(self) -> None:
        values = dict(self.frontend.diagnostics(), last_latency_ms=round(self.last_latency_ms, 1),
                      last_detections=self.last_detections, unexpected_errors=self.unexpected_errors)
        self.diag_pub.publish(diagnostics_msg(
            'rfm detector', self.backend, bool(self.counts['dropped_invalid'] + self.counts['dropped_no_gravity']),
            f'{self.counts["published"]} frames published', values, self.get_clock().now().nanoseconds))

    def destroy_node(self):
        self.worker.stop()
        return super().destroy_node()


def main(args=None):
    run_node(rclpy, DetectorNode, 'detector', args)


if __name__ == '__main__':
    main()
