"""From camera and IMU messages to detections: what the detector node runs, without ROS.

Frames (colour, camera_info, optionally depth; or simulated ground truth) must arrive in
stamp order (a jump far back, a looping bag, resets the state); gravity comes from the IMU's
complementary filter (waiting briefly for the IMU to catch up with a frame, and dropping
frames without recent IMU data) or a fixed vector; the gyroscope's orientation is attached
to each frame's detections (the matcher checks relative yaws with it), and so is the camera's
pose in a robot's odometry frame where /tf gives it (the matcher's motion prior). On a robot
the camera's acceleration the odometry measures is taken out of the accelerometer, so a
drive's start and stop do not tilt gravity. Messages are read by
their fields (:mod:`rfm_core.io`), so rclpy and rosbags messages both work.

:class:`FrameWorker` runs the detector on one thread with a short backlog (the oldest frame
waiting is dropped and counted when a new one arrives and the backlog is full), so nothing
queues without bound. A frame the detector is behind on (others wait after it) is sent with
its depth points and no detections (:meth:`DetectorFrontend.detect`, ``points_only``): the
matcher tracks it on the points at a fraction of the cost,
and the frames the detector catches up on are detected in full.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable

import numpy as np

from rfm_core.detection.base import Detector, DetectorInput, no_detections
from rfm_core.detection.gravity import GravityFilter
from rfm_core.io.images import depth_to_meters, image_to_rgb
from rfm_core.io.messages import camera_info_intrinsics, frame_detections_from_msg, imu_reading, stamp_to_ns
from rfm_core.io.sync import ApproximateTimeSynchronizer
from rfm_core.transforms import TransformBuffer
from rfm_core.observations import FrameObservations

__all__ = ['DetectorFrontend', 'FrameWorker', 'TIME_JUMP_NS', 'REPLACED_KEPT', 'DROP_COUNTERS']

TIME_JUMP_NS = 2_000_000_000      #: a stamp this much older than the last one: the bag looped
REPLACED_KEPT = 64                #: jobs a FrameWorker pushed out that wait for ``on_replaced``
#: the counter (in ``counts`` and on /diagnostics) behind each reason :meth:`DetectorFrontend.dropped`
#: gives, but ``unsynchronised``
DROP_COUNTERS = dict(busy='dropped_busy', invalid='dropped_invalid', no_gravity='dropped_no_gravity',
                     out_of_order='dropped_out_of_order', every_nth='skipped_nth')


class DetectorFrontend:
    """Synchronised frames in, :class:`FrameObservations` out. ``on_frame(kind, payload)`` is
    called with each frame to detect (``'images'``: the synchronised messages;
    ``'ground_truth'``: a FrameDetections message); :meth:`detect` turns it into detections.
    ``fixed_gravity``: "down" in the camera optical frame, or None to use the IMU."""

    def __init__(self, detector: Detector, on_frame: Callable, fixed_gravity=None, sync_slop_s: float = 0.05,
                 queue_size: int = 10, every_nth_frame: int = 1, imu_tau_s: float = 1.0, imu_max_age_s: float = 1.0,
                 imu_wait_s: float = 0.05, warn: Callable[[str], None] | None = None,
                 poll_imu: Callable[[], None] | None = None, odom_frame: str = '',
                 odometry_step_s: float = 0.05, odometry_lag_s: float = 0.1):
        self.detector = detector
        self.on_frame = on_frame
        self.fixed_gravity = None if fixed_gravity is None else np.asarray(fixed_gravity, float)
        if self.fixed_gravity is not None and not (self.fixed_gravity.shape == (3,)
                                                   and np.linalg.norm(self.fixed_gravity) > 1e-6):
            raise ValueError('gravity parameter must be a non-zero 3-vector')
        self.every_nth, self.imu_max_age_s, self.imu_wait_s = every_nth_frame, imu_max_age_s, imu_wait_s
        self.warn = warn or (lambda text: None)
        # takes the IMU samples queued so far (into add_imu): before each frame and while waiting for them
        self.poll_imu = poll_imu or (lambda: None)
        self.gravity_filter = GravityFilter(tau_s=imu_tau_s)
        self.odom_frame = odom_frame          # a robot's odometry: the camera's pose in it goes with each frame
        self.tf = TransformBuffer()
        self._tf_lock = threading.Lock()      # /tf arrives on the node's thread, frames are detected on the worker's
        self.odometry_step_ns, self.odometry_lag_ns = int(odometry_step_s * 1e9), int(odometry_lag_s * 1e9)
        self._camera_frame = None             # the colour images' frame: the IMU is taken to sit at its origin
        self._acceleration = (None, None)     # (stamp, the camera's acceleration then) of the newest odometry
        self.counts = dict(received=0, processed=0, published=0, points_only=0, odometry_only=0, dropped_busy=0,
                           dropped_invalid=0, dropped_no_gravity=0, dropped_out_of_order=0, skipped_nth=0)
        # colour, camera_info and depth when needed (ground truth arrives as one message)
        self.sync = (None if detector.name == 'ground_truth' else
                     ApproximateTimeSynchronizer(3 if detector.needs_depth else 2, int(sync_slop_s * 1e9), queue_size,
                                                 self._on_synced))
        self._last_stamp = None
        self._synced = 0

    # ------------------------------------------------------------------ inputs

    def _accept_stamp(self, stamp: int, what: str) -> bool:
        """Frames must arrive in stamp order; a jump far back (a looping bag) resets state."""
        last = self._last_stamp
        if last is not None and stamp <= last:
            if last - stamp <= TIME_JUMP_NS:
                self.counts['dropped_out_of_order'] += 1
                self.warn(f'{what} dropped: stamp {stamp} is not newer than the last ({last})')
                return False
            self.warn('time jumped backwards (bag loop?): resetting')
            if self.sync is not None:
                self.sync.reset()
            self.gravity_filter = GravityFilter(tau_s=self.gravity_filter.tau_s)
        self._last_stamp = stamp
        return True

    def add_image(self, index: int, msg) -> None:
        """A camera message: 0 colour (Image or CompressedImage), 1 camera_info, 2 depth."""
        stamp = stamp_to_ns(msg.header.stamp)
        if index == 0:
            self.counts['received'] += 1
            if not self._accept_stamp(stamp, 'image'):
                return
            self._camera_frame = msg.header.frame_id
        self.sync.add(index, stamp, msg)

    def _on_synced(self, *msgs) -> None:
        self._synced += 1
        if (self._synced - 1) % self.every_nth:
            self.counts['skipped_nth'] += 1
            return
        self.on_frame('images', msgs)

    def add_ground_truth(self, msg) -> None:
        """A simulated frame's ground-truth detections (backend ground_truth)."""
        self.counts['received'] += 1
        if self._accept_stamp(stamp_to_ns(msg.header.stamp), 'ground-truth frame'):
            self.on_frame('ground_truth', msg)

    def add_imu(self, msg) -> None:
        stamp, force, gyro = imu_reading(msg)
        if not self.gravity_filter.add(stamp, force, gyro, self._odometry_acceleration(stamp)):
            self.warn('IMU sample dropped: not finite, not near 1 g, or out of order')

    def _odometry_acceleration(self, stamp: int) -> np.ndarray | None:
        """On a robot (the odometry frame above the camera's on /tf), the camera's acceleration
        in the odometry frame, in the camera's axes, as the newest odometry has it, if that is
        within ``odometry_lag_s`` of ``stamp`` (/tf comes later than the IMU); else None.
        Computed once per odometry message."""
        if not (self.odom_frame and self._camera_frame):
            return None
        with self._tf_lock:
            newest = self.tf.newest(self.odom_frame, self._camera_frame)
            if newest is None or abs(stamp - newest) > self.odometry_lag_ns:
                return None
            if self._acceleration[0] != newest:
                self._acceleration = (newest, self.tf.acceleration(self.odom_frame, self._camera_frame, newest,
                                                                   self.odometry_step_ns))
            return self._acceleration[1]

    # ------------------------------------------------------------------ detection

    def detect(self, kind: str, payload, points_only: bool = False) -> FrameObservations | None:
        """Detections of one frame, the gyroscope's orientation attached when the IMU is
        recent; None when it has no gravity. ValueError for a malformed frame.
        ``points_only``: the frame's depth points and no detections (:meth:`Detector.points_only`;
        a frame with no depth is detected in full)."""
        self.poll_imu()
        if kind == 'ground_truth':
            obs = self.detector.perturb(frame_detections_from_msg(payload))
            obs.imu_rotation, obs.imu_epoch = None, 0        # the simulator's; the IMU's is attached
        else:
            rgb_msg, info, depth_msg = (tuple(payload) + (None,))[:3]
            stamp = stamp_to_ns(rgb_msg.header.stamp)
            gravity = self._gravity(stamp)
            if gravity is None:
                return None
            frame = DetectorInput(stamp, rgb_msg.header.frame_id, camera_info_intrinsics(info), gravity,
                                  rgb=image_to_rgb(rgb_msg),
                                  depth=depth_to_meters(depth_msg) if depth_msg is not None else None)
            if points_only and frame.depth is not None:
                obs = self.detector.points_only(frame)
                self.counts['points_only'] += 1
            else:
                obs = self.detector.detect(frame)
        return self._with_sensors(obs, self._odometry(obs.frame_id, obs.stamp_ns) if self.odom_frame else None)

    def odometry_only(self, kind: str, payload) -> FrameObservations | None:
        """A frame the detector has no time for, on a robot: its stamp, gravity, the
        gyroscope's orientation and the camera's pose in the odometry frame, without
        detections or depth points (the matcher carries it on the odometry, so the map logs
        a pose for it); None without odometry at its stamp, or gravity. Costs no image
        decoding, and does not wait: /tf is past a frame that waited behind another."""
        if kind != 'images' or not self.odom_frame:
            return None
        rgb_msg, info = tuple(payload)[:2]
        stamp = stamp_to_ns(rgb_msg.header.stamp)
        odometry = self._odometry(rgb_msg.header.frame_id, stamp, wait=False)
        gravity = self._gravity(stamp, wait=False) if odometry is not None else None
        if gravity is None:
            return None
        frame = DetectorInput(stamp, rgb_msg.header.frame_id, camera_info_intrinsics(info), gravity)
        self.counts['odometry_only'] += 1
        return self._with_sensors(no_detections(frame, self.detector.config, self.detector.name), odometry)

    def _with_sensors(self, obs: FrameObservations, odometry) -> FrameObservations:
        """``obs`` with the gyroscope's orientation at its stamp (where the IMU has it) and the
        camera's pose in the odometry frame (where given)."""
        found = self.gravity_filter.orientation_at(obs.stamp_ns)
        if found is not None:
            obs.imu_rotation, obs.imu_epoch = found
        if odometry is not None:
            obs.odometry, obs.odometry_epoch = odometry, 1
        return obs

    def _odometry(self, frame_id: str, stamp_ns: int, wait: bool = True) -> np.ndarray | None:
        """The camera's pose in the odometry frame at the image's stamp: interpolated once /tf
        has odometry past the stamp (waiting for it up to ``imu_wait_s``), else the newest
        within the buffer's tolerance; None without odometry."""
        deadline = time.monotonic() + (self.imu_wait_s if wait else 0.0)
        while True:
            with self._tf_lock:
                exact = self.tf.lookup(self.odom_frame, frame_id, stamp_ns, exact=True)
                near = exact if exact is not None else self.tf.lookup(self.odom_frame, frame_id, stamp_ns)
            if exact is not None or near is None or time.monotonic() >= deadline:
                return near
            time.sleep(0.002)

    def add_transform(self, parent: str, child: str, stamp_ns: int, matrix, static: bool = False) -> None:
        """A transform of /tf or /tf_static (a robot's odometry and the camera's mount)."""
        with self._tf_lock:
            problem = self.tf.add(parent, child, stamp_ns, matrix, static)
        if problem is not None:
            self.warn(f'/tf: {problem}')

    def _gravity(self, stamp: int, wait: bool = True):
        """Gravity at the image's stamp: the fixed one, else the IMU filter's; None when the
        IMU is stale. ``wait``: a frame to detect, for which the IMU gets a moment to catch up
        and which is counted and warned about as dropped; else neither."""
        if self.fixed_gravity is not None:
            return self.fixed_gravity / np.linalg.norm(self.fixed_gravity)
        # IMU and images travel on different topics: give the IMU a moment to catch up.
        deadline = time.monotonic() + (self.imu_wait_s if wait else 0.0)
        while time.monotonic() < deadline and (self.gravity_filter.last_stamp_ns or 0) < stamp:
            time.sleep(0.002)
            self.poll_imu()
        if self.gravity_filter.age_s(stamp) > self.imu_max_age_s:
            if not wait:
                return None
            self.counts['dropped_no_gravity'] += 1
            self.warn('frame dropped: no recent IMU data on "imu"; remap the IMU topic, '
                      'or set gravity_source:=parameter with gravity:=[gx, gy, gz]')
            return None
        return self.gravity_filter.gravity_at(stamp)

    def diagnostics(self) -> dict:
        """Counters for /diagnostics."""
        return dict(self.counts, dropped_unsynchronised=self.sync.stats.dropped if self.sync is not None else 0)

    def dropped(self) -> dict:
        """Colour frames received but not detected, by reason; ``unsynchronised``: never
        paired with camera_info (and depth) yet, so a frame waiting for its partner counts
        until the partner comes."""
        c = self.counts
        entered = c['received'] - c['dropped_out_of_order']
        unsynchronised = max(entered - self._synced, 0) if self.sync is not None else 0
        return dict({reason: c[key] for reason, key in DROP_COUNTERS.items()}, unsynchronised=unsynchronised)


class FrameWorker:
    """Runs ``work(*job)`` on its own thread, oldest job first, with at most ``backlog`` jobs
    waiting: a job submitted while the backlog is full pushes out the oldest waiting one, so
    nothing queues without bound; ``on_replaced(*job)`` is called with it, on the worker's
    thread, before the jobs submitted after it (it must be cheap; at most
    :data:`REPLACED_KEPT` wait for it, the oldest going unseen). ``backlog`` 1: the newest job
    wins. :attr:`waiting` tells ``work`` whether it is behind."""

    def __init__(self, work: Callable, on_replaced: Callable[..., None], name: str = 'worker', backlog: int = 1):
        self.work, self.on_replaced = work, on_replaced
        self.backlog = max(int(backlog), 1)
        self._pending: deque = deque()
        self._replaced: deque = deque(maxlen=REPLACED_KEPT)
        self._running = False
        self._stop = False
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def waiting(self) -> int:
        """Jobs waiting (not counting the one running)."""
        return len(self._pending)

    @property
    def idle(self) -> bool:
        """No job waiting (nor one pushed out) and none running."""
        with self._cv:
            return not self._pending and not self._replaced and not self._running

    def submit(self, *job) -> bool:
        """Queue ``job``; True when it pushed the oldest waiting one out."""
        with self._cv:
            pushed = len(self._pending) >= self.backlog
            if pushed:
                self._replaced.append(self._pending.popleft())
            self._pending.append(job)
            self._cv.notify()
        return pushed

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._replaced and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                replaced = bool(self._replaced)
                job = self._replaced.popleft() if replaced else self._pending.popleft()
                self._running = not replaced
            try:
                (self.on_replaced if replaced else self.work)(*job)
            finally:
                with self._cv:
                    self._running = False
