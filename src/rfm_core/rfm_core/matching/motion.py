"""The motion of a stream (not in the paper): what the view graph knows of how the camera
moves between frames.

Whether frames come from a continuous stream (a camera moving through the room) or are
separate views (photos seconds apart, an unordered collection) is decided from their timing,
per pair of frames: frames no more than ``max_frame_gap_s`` apart belong to one stream
segment, and so do a robot's frames across any gap its odometry measured. Within a segment
a camera cannot turn or move arbitrarily fast (the motion prior: each tracked frame must be
reachable from the previous one, each edge from its source keyframe), the gyroscope's
rotation between two frames checks a relative pose's yaw, and the frames objects placed give
the camera's velocity, which predicts where the next frame is; a robot's wheel odometry,
where the detector attached it, predicts it better, and carries the camera where objects and
depth points place nothing (:meth:`StreamMotion.odometry`): as the odometry of a pose-graph
SLAM system, it never lets the stream's map break apart, and objects seen again correct its
drift. A frame tracked on two objects alone is averaged with it
(:meth:`StreamMotion.with_odometry`). Across segments nothing is known of the motion.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rfm_core.geometry import Pose4, wrap_angle
from rfm_core.matching.graph import GraphStats, Keyframe, TrackState
from rfm_core.matching.relative_pose import RelativePose
from rfm_core.observations import FrameObservations, imu_relative_yaw
from rfm_core.settings import constant, setting

__all__ = ['MotionConfig', 'StreamMotion']


@dataclass(frozen=True)
class MotionConfig:
    max_frame_gap_s: float = setting(0.5, 'Frames further apart than this are separate views (photos): no motion '
                                     "prior between them; closer frames are one stream, and so are a robot's "
                                     'frames its odometry links (s)', lo=0.01, hi=3600.0)
    max_yaw_rate_deg_s: float = setting(90.0, 'Motion prior within a stream: fastest turn of the camera (deg/s)',
                                        lo=1.0, hi=3600.0)
    max_speed_m_s: float = setting(1.5, 'Motion prior within a stream: fastest motion of the camera (m/s)',
                                   lo=0.01, hi=100.0)
    motion_slack_deg: float = constant(10.0, 'Motion prior: turn allowed on top of rate x time (deg)',
                                       lo=0.0, hi=180.0)
    motion_slack_m: float = constant(0.3, 'Motion prior: motion allowed on top of speed x time (m)', lo=0.0, hi=10.0)
    velocity_window_s: float = constant(1.0, 'Motion prediction: the camera keeps the velocity of the frames '
                                        'objects placed over at most this long (s; 0: the position is held)',
                                        lo=0.0, hi=10.0)
    imu_yaw_tolerance_deg: float = constant(3.0, "Within a stream, a relative pose's yaw may differ from the "
                                            "gyroscope's by this (deg) ...", lo=0.1, hi=180.0)
    imu_yaw_drift_deg_s: float = setting(1.0, "... plus this per second between the frames (the gyroscope's bias; "
                                         'raise it for an uncalibrated IMU, deg/s)', lo=0.0, hi=90.0)
    odometry_error: float = setting(0.03, "A robot's wheel odometry checks relative poses within its error: this "
                                    'fraction of the distance driven and of the turn ...', lo=0.0, hi=1.0)
    odometry_drift_deg_s: float = setting(1.0, '... plus this yaw drift per second (deg/s) ...', lo=0.0, hi=90.0)
    odometry_slack_m: float = constant(0.1, "... plus a relative pose's own error (m; the averaging's outlier "
                                       'threshold)', lo=0.0, hi=10.0)
    odometry_weight: float = constant(2.0, "On a robot, a frame tracked on fewer objects than an edge needs "
                                      'unchecked takes the mean of that pose and the one the odometry carries '
                                      'it to, the odometry weighing this many objects (as the averaging weighs '
                                      'a motion link)', lo=0.0, hi=100.0)


class StreamMotion:
    """The stream's segments, the motion prior, the gyroscope's check and the camera's
    velocity (see the module); rejections are counted in ``stats``."""

    def __init__(self, config: MotionConfig, stats: GraphStats):
        self.config, self.stats = config, stats
        self.segment = -1                     # the current stream segment
        self._last = None                     # the previous frame (any frame: the stream's timing)
        self._placed: list = []               # (keyframe id, stamp, T_keyframe_frame.t) of frames objects placed
        self._carried = (None, np.zeros(3))   # (motion-placed keyframe id, the velocity carried into it)

    def continues(self, obs: FrameObservations) -> bool:
        """Whether a frame continues the stream of the previous one: no more than
        ``max_frame_gap_s`` later, or later by any time a robot's odometry measured the
        motion over (the detector that had no time for some frames breaks no stream); a new
        segment begins where it does not."""
        last, self._last = self._last, obs
        gap = obs.stamp_ns - last.stamp_ns if last is not None else 0
        stream = 0 < gap and (gap <= self.config.max_frame_gap_s * 1e9 or self.odometry(last, obs) is not None)
        if not stream:
            self.segment += 1
            self.stats.segments += 1
        return stream

    def observe(self, state: TrackState | None) -> None:
        """A frame was localized (or a keyframe made): a sample of the motion when objects
        placed it; None: the stream broke."""
        if state is None:
            self._placed = []
        elif state.verified_ns is None:               # placed by objects: a sample of the motion
            window = self.config.velocity_window_s * 1e9
            self._placed = [p for p in self._placed
                            if p[0] == state.keyframe_id and 0 <= state.stamp_ns - p[1] <= window]
            self._placed.append((state.keyframe_id, state.stamp_ns, np.asarray(state.pose.t, float)))

    def carry(self, keyframe_id: int, velocity: np.ndarray) -> None:
        """A keyframe placed by the motion: the camera keeps ``velocity`` through it."""
        self._carried = (keyframe_id, velocity)

    def velocity(self, prev: TrackState | None) -> np.ndarray:
        """The camera's velocity (m/s) in the reference keyframe's frame over the frames
        objects placed on it within ``velocity_window_s`` (on a keyframe a motion edge
        placed: the velocity carried into it); zero when unknown. ``prev``: the last frame
        localized."""
        if prev is not None and prev.verified_ns is not None:     # on a keyframe the motion placed
            return self._carried[1] if self._carried[0] == prev.keyframe_id else np.zeros(3)
        if prev is None or len(self._placed) < 2:
            return np.zeros(3)
        # (observe keeps only samples on prev's keyframe, prev's the last)
        _, first_ns, first_t = self._placed[0]
        _, last_ns, last_t = self._placed[-1]
        dt = (last_ns - first_ns) / 1e9
        if dt < 0.2:
            return np.zeros(3)
        v = (last_t - first_t) / dt
        speed = float(np.linalg.norm(v))
        return v if speed <= self.config.max_speed_m_s else v * (self.config.max_speed_m_s / speed)

    def predicted_pose(self, prev: TrackState | None, reference: Keyframe, obs: FrameObservations) -> Pose4 | None:
        """T_reference_frame as a robot's odometry measured it; else as the previous tracked
        frame's position, moved on at the camera's recent velocity, and the gyroscope's yaw
        predict it; None without a previous frame (the stream broke), or without odometry, a
        previous frame on the reference or a gyroscope."""
        if prev is None:
            return None
        odometry = self.carried(prev, reference, obs)
        if odometry is not None:
            return odometry
        if prev.keyframe_id != reference.keyframe_id:
            return None
        measured = self.imu_yaw(reference.observations, obs)
        if measured is None:
            return None
        dt = (obs.stamp_ns - prev.stamp_ns) / 1e9
        return Pose4(measured[0], np.asarray(prev.pose.t) + self.velocity(prev) * max(dt, 0.0))

    @staticmethod
    def odometry(a: FrameObservations, b: FrameObservations) -> Pose4 | None:
        """T_a_b between the two frames' gravity-aligned camera frames as a robot's odometry
        measured it (both carry it, of one epoch; its yaw and translation), else None."""
        if a.odometry is None or b.odometry is None or not a.odometry_epoch or a.odometry_epoch != b.odometry_epoch:
            return None
        camera = np.linalg.inv(a.odometry) @ b.odometry                 # T_acam_bcam
        m = a.rotation_aligned_from_camera @ camera[:3, :3] @ b.rotation_aligned_from_camera.T
        t = a.rotation_aligned_from_camera @ camera[:3, 3]
        return Pose4(float(np.arctan2(m[1, 0], m[0, 0])), t)

    def carried(self, prev: TrackState | None, reference: Keyframe, obs: FrameObservations) -> Pose4 | None:
        """T_reference_frame as the odometry carries the camera on from the previous frame
        localized on the reference (T_reference_prev, then the odometry's motion since),
        or from the reference itself; None without odometry."""
        if prev is not None and prev.keyframe_id == reference.keyframe_id and prev.observations is not None:
            step = self.odometry(prev.observations, obs)
            if step is not None:
                return prev.pose @ step
        return self.odometry(reference.observations, obs)

    def with_odometry(self, rel: RelativePose, prev: TrackState | None, reference: Keyframe,
                      obs: FrameObservations, min_objects: int) -> RelativePose:
        """``rel`` (T_reference_frame, tracked on objects) as the weighted mean with the pose
        the odometry carries the frame to (:meth:`carried`), where ``rel`` rests on fewer
        than ``min_objects`` objects: two boxes fix a pose only as well as their noise, and a
        robot's odometry from the frame tracked just before measures the same motion
        (``odometry_weight``)."""
        if len(rel.inliers) >= min_objects:
            return rel
        carried = self.carried(prev, reference, obs)
        if carried is None:
            return rel
        w = self.config.odometry_weight / (self.config.odometry_weight + len(rel.inliers))
        yaw = rel.pose.yaw + w * wrap_angle(carried.yaw - rel.pose.yaw)
        t = np.asarray(rel.pose.t) + w * (np.asarray(carried.t) - np.asarray(rel.pose.t))
        return replace(rel, pose=Pose4(float(yaw), t))

    def reachable(self, motion: Pose4, stamp_a: int, stamp_b: int) -> bool:
        """The motion prior: a camera cannot turn or move arbitrarily fast. Catches the
        quarter-turn flips and look-alike matches that two objects cannot rule out."""
        cfg = self.config
        dt = abs(stamp_b - stamp_a) / 1e9
        if (np.degrees(abs(motion.yaw)) > cfg.max_yaw_rate_deg_s * dt + cfg.motion_slack_deg
                or np.linalg.norm(motion.t) > cfg.max_speed_m_s * dt + cfg.motion_slack_m):
            self.stats.implausible += 1
            return False
        return True

    def imu_yaw(self, a: FrameObservations, b: FrameObservations):
        """(yaw of T_a_b as the gyroscope measured it, the deviation allowed in deg), or None
        when the frames share no integration epoch."""
        yaw = imu_relative_yaw(a, b)
        if yaw is None:
            return None
        cfg = self.config
        allowed = cfg.imu_yaw_tolerance_deg + cfg.imu_yaw_drift_deg_s * abs(b.stamp_ns - a.stamp_ns) / 1e9
        return yaw, allowed

    def sensors_agree(self, t_a_b: Pose4, a: FrameObservations, b: FrameObservations) -> bool:
        """Whether a relative pose agrees with what the sensors measured between the two
        frames: its yaw with the gyroscope's rotation, and on a robot its yaw and translation
        with the wheel odometry's motion, within the odometry's error over the way
        (``odometry_error``, ``odometry_drift_deg_s``, ``odometry_slack_m``). True for what
        the frames do not share (an integration epoch, an odometry epoch)."""
        measured = self.imu_yaw(a, b)
        if measured is not None:
            yaw, allowed = measured
            if np.degrees(abs(wrap_angle(t_a_b.yaw - yaw))) > allowed:
                self.stats.imu_rejected += 1
                return False
        odometry = self.odometry(a, b)
        if odometry is None:
            return True
        cfg = self.config
        distance = float(np.linalg.norm(odometry.t[:2]))
        yaw_error = (cfg.odometry_error * abs(odometry.yaw)
                     + np.radians(cfg.odometry_drift_deg_s) * abs(b.stamp_ns - a.stamp_ns) / 1e9)
        if (abs(wrap_angle(t_a_b.yaw - odometry.yaw)) > np.radians(cfg.imu_yaw_tolerance_deg) + yaw_error
                or np.linalg.norm(np.asarray(t_a_b.t) - odometry.t)
                > cfg.odometry_slack_m + (cfg.odometry_error + yaw_error) * distance):
            self.stats.odometry_rejected += 1
            return False
        return True

    def plausible(self, rel: RelativePose | None, a: FrameObservations, b: FrameObservations) -> RelativePose | None:
        """``rel`` (T_a_b) between two frames of one stream segment if the motion prior and
        the sensors (:meth:`sensors_agree`) allow it."""
        if (rel is None or not self.reachable(rel.pose, a.stamp_ns, b.stamp_ns)
                or not self.sensors_agree(rel.pose, a, b)):
            return None
        return rel
