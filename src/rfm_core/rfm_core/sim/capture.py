"""A simulated RGB-D + IMU capture of a room, written as an ordinary ROS 2 bag.

The bag carries what a RealSense-style driver publishes (no ground truth among them):

==============================  =================================  =====================
topic                           type                               notes
==============================  =================================  =====================
/camera/color/image_raw         sensor_msgs/Image (rgb8)           per frame
/camera/color/camera_info       sensor_msgs/CameraInfo             per frame
/camera/depth/image_raw         sensor_msgs/Image (16UC1 mm        aligned to colour,
                                or 32FC1 m)                        0 / NaN = no depth
/camera/depth/camera_info       sensor_msgs/CameraInfo             per frame
/imu/data                       sensor_msgs/Imu                    ``imu_rate_hz``, camera
                                                                   optical frame
/tf_static                      tf2_msgs/TFMessage                 latched: camera_link ->
                                                                   optical frame (and a
                                                                   robot's base_link ->
                                                                   camera_link)
/odom, /tf                      nav_msgs/Odometry, odom ->         a robot's wheel
                                base_link                          odometry,
                                                                   ``odom_rate_hz``
==============================  =================================  =====================

and ground truth on separate topics, which the pipeline never reads:

- ``/ground_truth/camera_pose`` (geometry_msgs/PoseStamped, frame ``map``): per frame, the
  pose of the camera optical frame (camera-to-map);
- ``/ground_truth/objects`` (rfm_msgs/ObjectMap, latched): every object, ids 1..N;
- ``/ground_truth/detections`` (rfm_msgs/FrameDetections): per frame, the full (amodal)
  boxes of the objects visible in it, in the camera frame, with their visible fraction.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from rfm_core.detection.base import DetectorInput
from rfm_core.geometry import Pose4, gravity_aligned_rotation
from rfm_core.observations import CameraIntrinsics, FrameObservations
from rfm_core.sim.render import NoiseModel, Renderer, RenderOutput
from rfm_core.sim.furniture import FURNITURE_STYLES
from rfm_core.sim.room import STYLES, Room, generate_room
from rfm_core.io.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS, OPTICAL_FRAME
from rfm_core.sim.trajectory import CAPTURE_STYLES, Trajectory, imu_samples, make_trajectory, wheel_odometry

__all__ = ['CaptureConfig', 'SimFrame', 'Capture', 'TOPICS', 'OPTICAL_FRAME', 'START_NS']

BASE_FRAME = 'camera_link'
ROBOT_BASE_FRAME = 'base_link'          #: a robot's base (REP 105), under odom
ODOM_FRAME = 'odom'
START_NS = 1_700_000_000 * 1_000_000_000      # bag time of the first frame
TOPICS = {**CAMERA_TOPICS, **GROUND_TRUTH_TOPICS}
# camera_link (x forward, y left, z up) -> optical frame (x right, y down, z forward)
_LINK_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0],
                               [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


@dataclass
class CaptureConfig:
    """Everything that defines a capture; the same config gives the same bytes."""

    seed: int = 0
    room_style: str = 'plain'             #: plain | textured (rfm_core.sim.room.STYLES)
    capture: str = 'handheld'             #: one of sim.trajectory.CAPTURE_STYLES
    frames: int = 100
    fps: float = 30.0                     #: frame rate of handheld / orbit captures
    width: int = 320
    height: int = 240
    hfov_deg: float = 70.0
    imu_rate_hz: float = 200.0
    odom_rate_hz: float = 50.0            #: a robot's wheel odometry
    depth_encoding: str = '16UC1'         #: 16UC1 (mm) | 32FC1 (m)
    min_visible_fraction: float = 0.001   #: ground-truth detections need this share of the image
    num_objects: tuple = (10, 40)
    noise: NoiseModel = field(default_factory=NoiseModel)
    trajectory_seed: int = -1             #: >= 0: another trajectory through the same room
    camera_height: tuple = ()             #: (min, max) m of a handheld / robot camera; (): the style's
    sparse_gap_s: tuple = (1.0, 1.0)      #: seconds between sparse views (a range: irregular photos)
    furniture: str = 'boxes'              #: boxes | parts (tables on legs, open shelves, ...: sim.furniture)
    clutter: bool = False                 #: rugs, pictures, door frames, radiators, cables (no ground truth)
    start_s: float = 0.0                  #: bag time of the first frame after START_NS (a later session)

    def __post_init__(self):
        if self.room_style not in STYLES:
            raise ValueError(f'room_style must be one of {STYLES}')
        if self.furniture not in FURNITURE_STYLES:
            raise ValueError(f'furniture must be one of {FURNITURE_STYLES}')
        if self.capture not in CAPTURE_STYLES:
            raise ValueError(f'capture must be one of {CAPTURE_STYLES}')
        if self.depth_encoding not in ('16UC1', '32FC1'):
            raise ValueError("depth_encoding must be '16UC1' (mm) or '32FC1' (m)")
        if self.width < 16 or self.height < 16 or self.frames < 1:
            raise ValueError('need at least 16x16 pixels and one frame')
        if isinstance(self.noise, dict):
            self.noise = NoiseModel(**self.noise)
        self.num_objects = tuple(self.num_objects)
        self.camera_height = tuple(float(v) for v in self.camera_height)
        self.sparse_gap_s = tuple(float(v) for v in self.sparse_gap_s)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        f = self.width / 2.0 / np.tan(np.radians(self.hfov_deg) / 2.0)
        return CameraIntrinsics(f, f, (self.width - 1) / 2.0, (self.height - 1) / 2.0,
                                self.width, self.height)

    def to_json(self) -> str:
        d = asdict(self)
        for key in NoiseModel.ARTEFACTS:
            if d['noise'][key] == asdict(NoiseModel())[key]:
                del d['noise'][key]
        for key, default in (('trajectory_seed', -1), ('furniture', 'boxes'), ('clutter', False),
                             ('camera_height', ()), ('sparse_gap_s', (1.0, 1.0)), ('start_s', 0.0),
                             ('odom_rate_hz', 50.0)):
            value = tuple(d[key]) if isinstance(d[key], list) else d[key]
            if value == default:              # defaults left out: older bags stay identical
                del d[key]
        return json.dumps(d, sort_keys=True)


@dataclass
class SimFrame:
    index: int
    stamp_ns: int
    rotation: np.ndarray         #: (3, 3) camera-to-map
    position: np.ndarray         #: (3,) camera center in the map frame
    render: RenderOutput
    ground_truth: FrameObservations   #: visible objects, boxes in the gravity-aligned camera frame

    @property
    def pose_matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.rotation, self.position
        return m

    def detector_input(self) -> DetectorInput:
        """The frame as a detector sees it: colour, depth (m), intrinsics, true gravity."""
        truth = self.ground_truth
        return DetectorInput(self.stamp_ns, truth.frame_id, truth.intrinsics, truth.gravity_cam,
                             self.render.rgb, self.render.depth)

    def aligned_from_map(self) -> Pose4:
        """T_aligned_map: the true 4-DoF pose mapping the map frame into this frame's
        gravity-aligned camera frame (what relative poses between keyframes compose)."""
        return aligned_from_map(self.rotation, self.position)


def aligned_from_map(rotation, position) -> Pose4:
    """T_aligned_map of a camera with orientation ``rotation`` (camera-to-map) at ``position``."""
    gravity_cam = rotation.T @ np.array([0.0, 0.0, -1.0])
    r = gravity_aligned_rotation(gravity_cam) @ rotation.T
    return Pose4.from_matrix(np.c_[r, -r @ position], atol=1e-6)


def _shifted(depth: np.ndarray, shift) -> np.ndarray:
    """``depth`` moved by (dx, dy) pixels; what moves in from the border is missing."""
    dx, dy = (int(v) for v in shift)
    out = np.full_like(depth, np.nan)
    h, w = depth.shape
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = depth[max(-dy, 0):h + min(-dy, 0),
                                                                       max(-dx, 0):w + min(-dx, 0)]
    return out


class Capture:
    """The room, trajectory and renderer of one configuration."""

    def __init__(self, config: CaptureConfig):
        self.config = config
        seeds = np.random.SeedSequence(config.seed).spawn(4)
        self.room: Room = generate_room(int(seeds[0].generate_state(1)[0]), config.room_style,
                                        config.num_objects, furniture=config.furniture, clutter=config.clutter)
        trajectory_seed = (int(seeds[1].generate_state(1)[0]) if config.trajectory_seed < 0 else
                           int(np.random.SeedSequence([config.seed, config.trajectory_seed]).generate_state(1)[0]))
        self.trajectory: Trajectory = make_trajectory(
            self.room, config.capture, config.frames, config.fps, seed=trajectory_seed,
            height=config.camera_height or None, sparse_gap_s=config.sparse_gap_s)
        self.intrinsics = config.intrinsics
        self.renderer = Renderer(self.room, self.intrinsics, config.noise)
        self._noise_seed = int(seeds[2].generate_state(1)[0])
        self._imu_seed = int(seeds[3].generate_state(1)[0])

    def stamp_ns(self, t: float) -> int:
        return START_NS + int(round((self.config.start_s + t) * 1e9))

    def frames(self, indices=None) -> Iterator[SimFrame]:
        """Render every frame in order, or only those at ``indices`` (faster; their sensor
        noise is then drawn differently from a full pass)."""
        wanted = None if indices is None else set(int(i) for i in indices)
        rng = np.random.default_rng(self._noise_seed)
        nm = self.config.noise
        camera = np.random.default_rng([self._noise_seed, 7])     # the camera's own artefacts
        r = nm.registration_offset_px
        offsets = [(dx, dy) for dx in range(-r, r + 1) for dy in range(-r, r + 1) if dx or dy]
        shift = offsets[camera.integers(len(offsets))] if offsets else (0, 0)
        log_gain = 0.0
        for i in range(len(self.trajectory)):
            if wanted is not None and i not in wanted:
                continue
            rotation = self.trajectory.rotations[i]
            position = self.trajectory.positions[i]
            out = self.renderer.render(rotation, position, rng)
            if nm.exposure_drift > 0:                   # auto-exposure wanders, slowly
                log_gain = 0.9 * log_gain + camera.normal(0.0, nm.exposure_drift)
                out.rgb = np.clip(np.rint(out.rgb * np.exp(log_gain)), 0, 255).astype(np.uint8)
            if np.any(shift):                           # depth registered to colour a pixel off
                out.depth = _shifted(out.depth, shift)
            stamp = self.stamp_ns(self.trajectory.times[i])
            yield SimFrame(i, stamp, rotation, position, out,
                           self.ground_truth_detections(rotation, position, out, stamp))

    def ground_truth_detections(self, rotation, position, out: RenderOutput,
                                stamp_ns: int) -> FrameObservations:
        """Full boxes of the objects visible in a rendered frame (gravity-aligned camera frame)."""
        gravity_cam = rotation.T @ np.array([0.0, 0.0, -1.0])
        t_aligned_map = aligned_from_map(rotation, position)
        min_pixels = self.config.min_visible_fraction * self.intrinsics.width * self.intrinsics.height
        keep = np.flatnonzero(out.visible_pixels >= max(min_pixels, 1))
        visibility = np.clip(out.visible_pixels[keep] / np.maximum(out.amodal_area[keep], 1), 0, 1)
        boxes = t_aligned_map.transform_boxes(self.room.boxes[keep]) if len(keep) else np.zeros((0, 7))
        return FrameObservations(
            stamp_ns=stamp_ns, frame_id=OPTICAL_FRAME, intrinsics=self.intrinsics,
            gravity_cam=gravity_cam, boxes=boxes, scores=np.ones(len(keep)),
            labels=[self.room.objects[k].label for k in keep],
            boxes_2d=out.boxes_2d[keep], visibility=visibility, object_ids=keep + 1,
            backend='ground_truth')

    def odometry(self, times) -> tuple[np.ndarray, np.ndarray]:
        """A robot capture's wheel odometry at ``times`` (s): (T, 3) base_link's (x, y, heading)
        in odom and (T, 2) velocities (:func:`~rfm_core.sim.trajectory.wheel_odometry`)."""
        nm = self.config.noise
        return wheel_odometry(self.trajectory.path, times, self._imu_seed, nm.odom_scale_error, nm.odom_turn_error,
                              nm.odom_yaw_bias_dps)

    def mount(self) -> np.ndarray:
        """A robot capture's base_link -> camera_link (4x4): the camera ahead of the base's
        centre at its height, level."""
        from rfm_core.io.messages import planar_matrix  # noqa: PLC0415

        path = self.trajectory.path
        return planar_matrix(path.MOUNT_X, 0.0, 0.0, path.height)

    def camera_odometry(self) -> dict:
        """{stamp_ns: 4x4 camera optical frame in odom} of every frame of a robot capture, as
        its TF tree gives it (odom -> base_link -> camera_link -> optical frame)."""
        from rfm_core.io.messages import planar_matrix  # noqa: PLC0415

        mount = self.mount() @ _LINK_FROM_OPTICAL
        odom, _ = self.odometry(self.trajectory.times)
        return {self.stamp_ns(t): planar_matrix(*o) @ mount for t, o in zip(self.trajectory.times, odom)}

    # ------------------------------------------------------------------ bag writing

    def write_bag(self, path, progress: Callable[[int, int], None] | None = None) -> dict:
        """Write the capture as a rosbag2 MCAP directory at ``path`` (must not exist)."""
        from rfm_core.io.bag import BagWriter  # noqa: PLC0415
        from rfm_core.io.images import numpy_to_image  # noqa: PLC0415
        from rfm_core.io.messages import (  # noqa: PLC0415
            camera_info_msg, frame_detections_to_msg, header, imu_msg, object_map_msg, odometry_msg, planar_matrix,
            pose_stamped_msg, transform_stamped_msg,
        )

        cfg = self.config
        nm = cfg.noise
        imu = imu_samples(self.trajectory, cfg.imu_rate_hz, seed=self._imu_seed,
                          gyro_bias=np.radians(nm.imu_gyro_bias_dps), accel_bias=nm.imu_accel_bias)
        imu_stamps = [self.stamp_ns(t) + int(round(nm.imu_time_offset_ms * 1e6)) for t in imu.times]
        delays = np.random.default_rng([self._noise_seed, 8])     # depth stamped after colour
        robot = self.trajectory.path                   # a wheeled base: its odometry on /odom and /tf
        topics = {k: v for k, v in TOPICS.items() if robot is not None or k not in ('odom', 'tf')}
        counts = {topic: 0 for topic in topics.values()}
        with BagWriter(path) as bag:
            make = bag.make
            bag.set_metadata('rfm.sim.config', cfg.to_json())
            for key, topic in topics.items():
                msgtype = {
                    'color': 'sensor_msgs/msg/Image', 'depth': 'sensor_msgs/msg/Image',
                    'color_info': 'sensor_msgs/msg/CameraInfo',
                    'depth_info': 'sensor_msgs/msg/CameraInfo', 'imu': 'sensor_msgs/msg/Imu',
                    'tf_static': 'tf2_msgs/msg/TFMessage', 'tf': 'tf2_msgs/msg/TFMessage',
                    'odom': 'nav_msgs/msg/Odometry',
                    'gt_pose': 'geometry_msgs/msg/PoseStamped',
                    'gt_objects': 'rfm_msgs/msg/ObjectMap',
                    'gt_detections': 'rfm_msgs/msg/FrameDetections'}[key]
                bag.add_topic(topic, msgtype, latched=key in ('tf_static', 'gt_objects'),
                              reliable=key != 'imu')

            def write(key, stamp, msg):
                bag.write(TOPICS[key], stamp, msg)
                counts[TOPICS[key]] += 1

            start = self.stamp_ns(0.0)
            mounts = [transform_stamped_msg(_LINK_FROM_OPTICAL, start, BASE_FRAME, OPTICAL_FRAME, make)]
            if robot is not None:                       # base_link -> camera_link: the camera's mount
                mounts.append(transform_stamped_msg(self.mount(), start, ROBOT_BASE_FRAME, BASE_FRAME, make))
            write('tf_static', start, make('tf2_msgs/msg/TFMessage', transforms=mounts))
            write('gt_objects', start, object_map_msg(
                self.room.boxes, self.room.labels, np.arange(len(self.room.objects)) + 1,
                start, 'map', make=make))
            next_imu = next_odom = 0
            odom_times = np.arange(0.0, self.trajectory.times[-1] + 1e-9, 1.0 / cfg.odom_rate_hz)
            odom, odom_velocity = self.odometry(odom_times) if robot is not None else (np.zeros((0, 3)), None)
            odom_stamps = [self.stamp_ns(t) for t in odom_times[:len(odom)]]

            def write_imu_until(stamp_ns):
                """IMU samples (and a robot's odometry) up to ``stamp_ns``, so the bag stays in time order."""
                nonlocal next_imu, next_odom
                while next_imu < len(imu_stamps) and imu_stamps[next_imu] <= stamp_ns:
                    write('imu', imu_stamps[next_imu], imu_msg(
                        imu.linear_acceleration[next_imu], imu.angular_velocity[next_imu],
                        imu_stamps[next_imu], OPTICAL_FRAME, make=make))
                    next_imu += 1
                while next_odom < len(odom_stamps) and odom_stamps[next_odom] <= stamp_ns:
                    stamp = odom_stamps[next_odom]
                    write('odom', stamp, odometry_msg(odom[next_odom], odom_velocity[next_odom], stamp, ODOM_FRAME,
                                                      ROBOT_BASE_FRAME, make=make))
                    write('tf', stamp, make('tf2_msgs/msg/TFMessage', transforms=[transform_stamped_msg(
                        planar_matrix(*odom[next_odom]), stamp, ODOM_FRAME, ROBOT_BASE_FRAME, make)]))
                    next_odom += 1

            for frame in self.frames():
                write_imu_until(frame.stamp_ns)
                stamp = frame.stamp_ns
                image_header = header(make, stamp, OPTICAL_FRAME)
                write('color', stamp, numpy_to_image(frame.render.rgb, 'rgb8', image_header, make=make))
                write('color_info', stamp, camera_info_msg(self.intrinsics, stamp, OPTICAL_FRAME, make))
                depth = frame.render.depth
                depth_stamp = stamp
                if nm.depth_delay_ms[1] > 0:
                    depth_stamp += int(round(delays.uniform(*nm.depth_delay_ms) * 1e6))
                depth_header = image_header if depth_stamp == stamp else header(make, depth_stamp, OPTICAL_FRAME)
                if cfg.depth_encoding == '16UC1':
                    mm = np.where(np.isfinite(depth), np.rint(depth * 1000.0), 0)
                    depth_msg = numpy_to_image(np.clip(mm, 0, 65535).astype(np.uint16), '16UC1',
                                               depth_header, make=make)
                else:
                    depth_msg = numpy_to_image(depth.astype(np.float32), '32FC1', depth_header,
                                               make=make)
                write('depth', depth_stamp, depth_msg)
                write('depth_info', depth_stamp, camera_info_msg(self.intrinsics, depth_stamp, OPTICAL_FRAME, make))
                write('gt_pose', stamp, pose_stamped_msg(frame.pose_matrix, stamp, 'map', make))
                write('gt_detections', stamp, frame_detections_to_msg(frame.ground_truth, make))
                if progress is not None:
                    progress(frame.index + 1, len(self.trajectory))
            write_imu_until(max(imu_stamps[-1] if imu_stamps else 0, odom_stamps[-1] if odom_stamps else 0))
        return {'path': str(Path(path)), 'messages': counts, 'objects': len(self.room.objects)}
