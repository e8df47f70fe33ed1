"""rfm detector node: per-frame metric 3D boxes and embeddings (paper section 3.1).

Subscribes (all remappable; sensor-data QoS, so reliable and best-effort publishers connect):
  rgb/image (sensor_msgs/Image: rgb8, bgr8, mono8; or with image_transport:=compressed,
  rgb/image/compressed: sensor_msgs/CompressedImage, JPEG or PNG), rgb/camera_info, depth/image (16UC1 mm
  or 32FC1 m, registered to rgb; when the backend needs depth), imu (sensor_msgs/Imu, for
  gravity), ground_truth/detections (rfm_msgs/FrameDetections; backend ground_truth only).
Publishes:
  rfm/detections (rfm_msgs/FrameDetections), rfm/detection_markers (MarkerArray),
  /diagnostics (diagnostic_msgs/DiagnosticArray: counters, latency).

Frames are processed by one worker thread; a frame arriving while it is busy replaces the
waiting one (newest wins) and is counted as dropped, so nothing queues without bound.
Thin rclpy wrapper: the algorithms live in rfm_core.detection.
"""
from __future__ import annotations

import sys
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rfm_msgs.msg import FrameDetections
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
from visualization_msgs.msg import MarkerArray

from rfm_core.config import DetectorNodeConfig
from rfm_core.detection import make_detector
from rfm_core.detection.base import DetectorInput
from rfm_core.detection.gravity import GravityFilter
from rfm_core.geometry import box_corners
from rfm_core.io.images import depth_to_meters, image_to_rgb
from rfm_core.io.messages import (
    box_markers_msg, camera_info_intrinsics, frame_detections_from_msg, frame_detections_to_msg, imu_reading, stamp_to_ns,
)
from rfm_core.io.parameters import declare_config
from rfm_core.io.sync import ApproximateTimeSynchronizer
from rfm_core.matching.config import MONOCULAR_RANGE_ERROR

_TIME_JUMP_NS = 2_000_000_000      # a stamp this much older than the last one: bag looped


class DetectorNode(Node):

    def __init__(self, **kwargs):
        super().__init__('detector', **kwargs)
        self.config = cfg = declare_config(self, DetectorNodeConfig())
        self.backend, self.every_nth, self.image_transport = cfg.backend, cfg.every_nth_frame, cfg.image_transport
        self.gravity_source, self.imu_max_age_s, self.imu_wait_s = cfg.gravity_source, cfg.imu_max_age_s, cfg.imu_wait_s
        self.publish_markers, self.diagnostics_period = cfg.publish_markers, cfg.diagnostics_period_s
        self.detector = make_detector(self.backend, cfg.backend_config())
        if self.detector.monocular:
            error, per_m = MONOCULAR_RANGE_ERROR
            self.get_logger().info(
                f'{self.backend} judges distance from RGB alone: give the matcher and mapper '
                f'matching.range_error:={error} matching.range_error_per_m:={per_m} (rfm run does for '
                'ground_truth rgb)')
        self.fixed_gravity = np.asarray(cfg.gravity, dtype=np.float64)
        if self.gravity_source == 'parameter' and np.linalg.norm(self.fixed_gravity) < 1e-6:
            raise ValueError('gravity parameter must be a non-zero 3-vector')
        self.gravity_filter = GravityFilter(tau_s=cfg.imu_tau_s)

        self.counts = dict(received=0, processed=0, published=0, dropped_busy=0,
                           dropped_invalid=0, dropped_no_gravity=0, dropped_out_of_order=0,
                           skipped_nth=0)
        self.last_latency_ms = float('nan')
        self.last_detections = 0
        self._last_stamp = None
        self._synced = 0
        self._pending = None
        self._cv = threading.Condition()
        self._stop = False

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(FrameDetections, 'rfm/detections', reliable)
        self.marker_pub = (self.create_publisher(MarkerArray, 'rfm/detection_markers', reliable)
                           if self.publish_markers else None)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        sensor = qos_profile_sensor_data
        if self.backend == 'ground_truth':
            self.create_subscription(FrameDetections, 'ground_truth/detections',
                                     self._on_ground_truth, QoSProfile(depth=50))
            inputs = 'ground_truth/detections'
        else:
            self.uses_depth = self.detector.needs_depth
            n = 3 if self.uses_depth else 2
            self.sync = ApproximateTimeSynchronizer(n, int(cfg.sync_slop_s * 1e9), cfg.queue_size, self._on_synced)
            if self.image_transport == 'compressed':
                colour = 'rgb/image/compressed'
                self.create_subscription(CompressedImage, colour, lambda m: self._add(0, m), sensor)
            else:
                colour = 'rgb/image'
                self.create_subscription(Image, colour, lambda m: self._add(0, m), sensor)
            self.create_subscription(CameraInfo, 'rgb/camera_info', lambda m: self._add(1, m), sensor)
            if self.uses_depth:
                self.create_subscription(Image, 'depth/image', lambda m: self._add(2, m), sensor)
            inputs = f'{colour}, rgb/camera_info' + (', depth/image' if self.uses_depth else '')
        if self.gravity_source == 'imu' or self.backend == 'ground_truth':
            # gravity (unless given or simulated) and the gyroscope's orientation
            self.create_subscription(Imu, 'imu', self._on_imu, sensor)
            inputs += ', imu' if self.backend != 'ground_truth' else ', imu (optional)'
        self.create_timer(self.diagnostics_period, self._publish_diagnostics)
        self._worker = threading.Thread(target=self._work, name='detector_worker', daemon=True)
        self._worker.start()
        self.get_logger().info(f'detector ready: backend={self.backend}, inputs: {inputs}')

    # ------------------------------------------------------------------ inputs

    def _warn(self, text: str) -> None:
        self.get_logger().warning(text, throttle_duration_sec=5.0)

    def _accept_stamp(self, stamp: int, what: str) -> bool:
        """Frames must arrive in stamp order; a jump far back (a looping bag) resets state."""
        last = self._last_stamp
        if last is not None and stamp <= last:
            if last - stamp <= _TIME_JUMP_NS:
                self.counts['dropped_out_of_order'] += 1
                self._warn(f'{what} dropped: stamp {stamp} is not newer than the last ({last})')
                return False
            self.get_logger().info('time jumped backwards (bag loop?): resetting')
            if self.backend != 'ground_truth':
                self.sync.reset()
            self.gravity_filter = GravityFilter(tau_s=self.gravity_filter.tau_s)
        self._last_stamp = stamp
        return True

    def _add(self, index: int, msg) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        if index == 0:
            self.counts['received'] += 1
            if not self._accept_stamp(stamp, 'image'):
                return
        self.sync.add(index, stamp, msg)

    def _on_imu(self, msg: Imu) -> None:
        if not self.gravity_filter.add(*imu_reading(msg)):
            self._warn('IMU sample dropped: not finite, not near 1 g, or out of order')

    def _on_synced(self, *msgs) -> None:
        self._synced += 1
        if (self._synced - 1) % self.every_nth:
            self.counts['skipped_nth'] += 1
            return
        self._submit(('images', msgs))

    def _on_ground_truth(self, msg: FrameDetections) -> None:
        self.counts['received'] += 1
        if not self._accept_stamp(stamp_to_ns(msg.header.stamp), 'ground-truth frame'):
            return
        self._submit(('ground_truth', msg))

    def _submit(self, job) -> None:
        with self._cv:
            if self._pending is not None:
                self.counts['dropped_busy'] += 1      # newest wins
            self._pending = job
            self._cv.notify()

    # ------------------------------------------------------------------ processing

    def _work(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                job, self._pending = self._pending, None
            start = time.perf_counter()
            try:
                obs = self._process(*job)
            except (ValueError, RuntimeError) as exc:
                self.counts['dropped_invalid'] += 1
                self._warn(f'frame dropped: {exc}')
                continue
            except Exception as exc:  # noqa: BLE001 - never let a bad frame kill the node
                self.counts['dropped_invalid'] += 1
                self.get_logger().error(f'frame dropped, unexpected error: {exc!r}',
                                        throttle_duration_sec=5.0)
                continue
            if obs is None:
                continue
            self.counts['processed'] += 1
            self.last_latency_ms = 1e3 * (time.perf_counter() - start)
            self.last_detections = len(obs)
            try:
                self.pub.publish(frame_detections_to_msg(obs))
                self.counts['published'] += 1
                if self.marker_pub is not None:
                    self.marker_pub.publish(self._markers(obs))
            except Exception as exc:  # noqa: BLE001 - e.g. publishing during shutdown
                self.get_logger().debug(f'publish failed: {exc!r}')

    def _process(self, kind, payload):
        obs = self._detect(kind, payload)
        if obs is not None:
            self._attach_orientation(obs)
        return obs

    def _attach_orientation(self, obs) -> None:
        """The gyroscope's orientation at the frame (the matcher checks relative yaws with it),
        when the IMU is recent."""
        found = self.gravity_filter.orientation_at(obs.stamp_ns)
        if found is not None:
            obs.imu_rotation, obs.imu_epoch = found

    def _detect(self, kind, payload):
        if kind == 'ground_truth':
            obs = self.detector.perturb(frame_detections_from_msg(payload))
            obs.imu_rotation, obs.imu_epoch = None, 0        # the simulator's; the IMU's is attached
            return obs
        rgb_msg, info, depth_msg = (payload + (None,))[:3]
        stamp = stamp_to_ns(rgb_msg.header.stamp)
        intrinsics = camera_info_intrinsics(info)
        if self.gravity_source == 'imu':
            # IMU and images travel on different topics: give the IMU a moment to catch up.
            deadline = time.monotonic() + self.imu_wait_s
            while time.monotonic() < deadline and (self.gravity_filter.last_stamp_ns or 0) < stamp:
                time.sleep(0.002)
            if self.gravity_filter.age_s(stamp) > self.imu_max_age_s:
                self.counts['dropped_no_gravity'] += 1
                self._warn('frame dropped: no recent IMU data on "imu"; remap the IMU topic, '
                           'or set gravity_source:=parameter with gravity:=[gx, gy, gz]')
                return None
            gravity = self.gravity_filter.gravity()
        else:
            gravity = self.fixed_gravity / np.linalg.norm(self.fixed_gravity)
        frame = DetectorInput(stamp, rgb_msg.header.frame_id, intrinsics, gravity,
                              rgb=image_to_rgb(rgb_msg),
                              depth=depth_to_meters(depth_msg) if depth_msg is not None else None)
        return self.detector.detect(frame)

    # ------------------------------------------------------------------ outputs

    def _markers(self, obs) -> MarkerArray:
        """The frame's boxes in the camera's optical frame, coloured by score."""
        corners = box_corners(obs.boxes).reshape(-1, 8, 3) @ obs.rotation_aligned_from_camera   # aligned -> camera
        scores = np.asarray(obs.scores, float)
        return box_markers_msg(
            corners, [f'{label + " " if label else ""}{score:.2f}' for label, score in zip(obs.labels, scores)],
            corners[:, 4:].mean(1), np.stack([1.0 - scores, scores, np.full_like(scores, 0.2), np.ones_like(scores)], 1),
            obs.stamp_ns, obs.frame_id, line_width=0.01, text_size=0.08, text_colour=(1.0, 1.0, 1.0, 1.0),
            namespaces=('boxes', 'scores'))

    def _publish_diagnostics(self) -> None:
        status = DiagnosticStatus(name='rfm detector', hardware_id=self.backend)
        dropped = self.counts['dropped_invalid'] + self.counts['dropped_no_gravity']
        status.level = DiagnosticStatus.WARN if dropped else DiagnosticStatus.OK
        status.message = f'{self.counts["published"]} frames published'
        values = dict(self.counts)
        values['dropped_unsynchronised'] = self.sync.stats.dropped if self.backend != 'ground_truth' else 0
        values['last_latency_ms'] = round(self.last_latency_ms, 1)
        values['last_detections'] = self.last_detections
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [status]
        self.diag_pub.publish(msg)

    def destroy_node(self):
        with self._cv:
            self._stop = True
            self._cv.notify()
        return super().destroy_node()


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = DetectorNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:                 # a bad parameter: say which, exit non-zero
        print(f'detector: {exc}', file=sys.stderr)
        raise SystemExit(1) from None
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
