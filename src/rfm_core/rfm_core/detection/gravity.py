"""Gravity from an IMU: a complementary filter of accelerometer and gyroscope.

At rest the accelerometer reads +9.81 m/s^2 along "up"; while the camera moves, the
reading adds the camera's own acceleration, which averages out over a second or so. A
plain low-pass of the accelerometer therefore lags every rotation of the camera (several
degrees for a handheld camera). Here the estimate is rotated with the gyroscope between
samples (in the camera frame a fixed direction v moves as dv/dt = -w x v) and pulled
towards the accelerometer with time constant ``tau_s``. Without gyroscope readings it
degrades to the low-pass. Until ``tau_s`` of samples have come the estimate is their mean
(the first sample alone carries the camera's acceleration at that moment: about 5 deg on a
handheld start). A frame is given gravity as it was at its stamp (:meth:`gravity_at`: the
newest estimate turned back by the gyroscope), not as the camera has turned while the
detector was busy. Everything is in the IMU's frame (the camera optical frame, or rotated
into it by the caller).

The gyroscope is also integrated into an orientation (IMU frame -> a fixed frame that
drifts slowly with the gyroscope's bias): the rotation between two moments of one
integration epoch, which the matcher uses to check relative poses. A gap in the stream
(``max_gap_s``) or a sample without angular velocity starts a new epoch.

At rest (for ``rest_window_s`` the accelerometer reads 1 g within ``rest_tolerance`` and
the gyroscope less than ``rest_gyro_rad_s``) the accelerometer is gravity itself. If its
mean differs from the estimate by more than ``rest_reset_deg`` (a walk between two photos
leans the estimate with its accelerations), the estimate takes the accelerometer's mean at
once. If it also differs that much from the direction the gyroscope alone carried since the
estimate last started or took the accelerometer's mean, the camera was turned without the
gyroscope seeing it (a stretch of samples lost, a camera put down elsewhere): the
orientation starts a new epoch. (Taking the mean whenever the camera seems at rest was
measured worse on handheld walks: slow motion passes for rest, and its acceleration tilts
the estimate.) A sample whose accelerometer is out of range (a knock, a fast swing) still
turns the estimate and the orientation by its gyroscope reading.

A robot's wheel odometry measures the acceleration a drive's start and stop add (1-2 m/s^2
on a short drive: 6-12 deg of tilt, and a straight drive turns no gyroscope, so it passes for
rest). The caller passes it with each sample (:meth:`add`'s ``acceleration``) and it is taken
out before the sample is used, both by the filter and by the rest test.
"""
from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np

__all__ = ['GravityFilter']


def _orthonormal(m: np.ndarray) -> np.ndarray:
    """The rotation nearest ``m`` (a long product of rotations drifts off orthonormality)."""
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
    return math.degrees(math.acos(min(max(cos, -1.0), 1.0)))


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = math.sqrt(rotvec[0] * rotvec[0] + rotvec[1] * rotvec[1] + rotvec[2] * rotvec[2])
    if angle < 1e-12:
        return np.eye(3)
    k = rotvec / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * (kx @ kx)


class GravityFilter:

    #: standard gravity (m/s^2): the accelerometer's reading at rest
    G = 9.80665
    #: (m/s^2) a specific force outside this range is no reading of gravity
    FORCE_RANGE = (4.0, 20.0)
    #: (s) how far back the samples go that a frame's gravity and orientation are read from: a
    #: detector behind its camera on a slow machine takes frames seconds late
    HISTORY_S = 10.0
    #: at most this many of them (an IMU at several kHz)
    HISTORY_MAX = 20000

    def __init__(self, tau_s: float = 1.0, max_gap_s: float = 1.0, rest_window_s: float = 0.1,
                 rest_tolerance: float = 0.02, rest_gyro_rad_s: float = 0.05, rest_reset_deg: float = 5.0):
        if tau_s <= 0:
            raise ValueError('tau_s must be > 0')
        self.tau_s = float(tau_s)
        self.max_gap_s = float(max_gap_s)
        self.rest_window_s = float(rest_window_s)
        self.rest_tolerance = float(rest_tolerance)
        self.rest_gyro_rad_s = float(rest_gyro_rad_s)
        self.rest_reset_deg = float(rest_reset_deg)
        self._rest = deque()               # recent samples that look like rest: (stamp_ns, force)
        self._force = None
        self._carried = None               # gravity as the gyroscope alone carried it (see the module)
        self._since_start = 0              # samples since the estimate (re)started
        self._stamp_ns = None
        self._orientation = None          # IMU frame -> integration frame, None without gyroscope
        self._history = deque(maxlen=self.HISTORY_MAX)  # (stamp_ns, epoch, orientation or None, force), HISTORY_S
        self.epoch = 0                    # integration epoch of the orientation (0: none yet)
        self.samples = 0
        self.rejected = 0
        self.rest_resets = 0              # times the resting accelerometer contradicted the gyroscope

    def add(self, stamp_ns: int, specific_force, angular_velocity=None, acceleration=None) -> bool:
        """Add one IMU sample: specific force (m/s^2) and, optionally, angular velocity
        (rad/s) and the IMU's own acceleration (m/s^2, in its frame) where something else
        measures it (a robot's wheel odometry): it is taken out of the specific force, which
        leaves gravity (unless that leaves a force far from 1 g: a jump of the odometry).
        Returns False when its force is no reading of gravity (non-finite or far from 1 g in
        magnitude: only its angular velocity is used) or it is older than the last accepted
        sample (ignored)."""
        f = np.asarray(specific_force, dtype=np.float64).reshape(-1)
        norm = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]) if f.size == 3 else np.nan
        if acceleration is not None and np.isfinite(norm):
            g = f - np.asarray(acceleration, dtype=np.float64).reshape(3)
            g_norm = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2])
            if self.FORCE_RANGE[0] < g_norm < self.FORCE_RANGE[1]:
                f, norm = g, g_norm
        if self._stamp_ns is not None and stamp_ns < self._stamp_ns:
            self.rejected += 1
            return False
        w = None
        if angular_velocity is not None:
            w = np.asarray(angular_velocity, dtype=np.float64).reshape(3)
            w = w if np.all(np.isfinite(w)) else None
        dt = None if self._stamp_ns is None else (stamp_ns - self._stamp_ns) * 1e-9
        if not np.isfinite(norm) or not self.FORCE_RANGE[0] < norm < self.FORCE_RANGE[1]:
            self.rejected += 1                        # no reading of gravity: a knock, a swing
            if w is None or self._force is None or dt > self.max_gap_s:
                return False
            self._turn(w, dt)                         # but the gyroscope still saw the camera turn
            self._rest.clear()
            self._record(stamp_ns)
            return False
        if self._force is None or dt > self.max_gap_s:
            self._force = f.copy()
            self._carried = f.copy()
            self._orientation = None
            self._since_start = 1
        else:
            if w is not None:
                self._turn(w, dt)
            # until tau_s of samples have come, their mean (turned by the gyroscope): the
            # first sample alone carries the camera's acceleration at that moment
            self._since_start += 1
            alpha = max(1.0 - np.exp(-dt / self.tau_s), 1.0 / self._since_start)
            self._force += alpha * (f - self._force)
        self._at_rest(stamp_ns, f, norm, w)
        if w is None:
            self._orientation = None
        elif self._orientation is None:               # a new integration epoch
            self._orientation = np.eye(3)
            self.epoch += 1
        self._record(stamp_ns)
        self.samples += 1
        return True

    def _turn(self, w: np.ndarray, dt: float) -> None:
        """Carry the estimate and the orientation through the body's rotation ``w`` over ``dt``."""
        step = _rotation(w * dt)
        self._force = step.T @ self._force            # a fixed direction, seen from the body
        self._carried = step.T @ self._carried
        if self._orientation is not None:             # R <- R exp([w dt]x): body rates
            self._orientation = self._orientation @ step

    def _record(self, stamp_ns: int) -> None:
        self._history.append((int(stamp_ns), self.epoch, self._orientation, self._force.copy()))
        while stamp_ns - self._history[0][0] > self.HISTORY_S * 1e9:
            self._history.popleft()
        self._stamp_ns = int(stamp_ns)

    def _at_rest(self, stamp_ns: int, f: np.ndarray, norm: float, w) -> None:
        """Take gravity from the accelerometer once the camera has rested ``rest_window_s``."""
        still = (w is not None and abs(norm - self.G) <= self.rest_tolerance * self.G
                 and math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) < self.rest_gyro_rad_s)
        if not still:
            self._rest.clear()
            return
        self._rest.append((int(stamp_ns), f))
        while self._rest and stamp_ns - self._rest[0][0] > self.rest_window_s * 1e9:
            self._rest.popleft()
        if len(self._rest) < 3 or stamp_ns - self._rest[0][0] < 0.8 * self.rest_window_s * 1e9:
            return
        mean = np.mean([g for _, g in self._rest], axis=0)
        if _angle_deg(mean, self._force) > self.rest_reset_deg:
            self._force = mean                # gravity from the resting accelerometer
            if _angle_deg(mean, self._carried) > self.rest_reset_deg:
                self._orientation = None      # turned unseen: the orientation starts a new epoch (below)
                self.rest_resets += 1
            self._carried = mean

    def orientation(self) -> np.ndarray | None:
        """(3, 3) IMU frame -> integration frame at the last sample, or None (no gyroscope);
        compare only orientations of one :attr:`epoch`."""
        if self._orientation is None:
            return None
        return _orthonormal(self._orientation)

    def _nearest(self, stamp_ns: int, max_gap_s: float):
        """The recent sample nearest ``stamp_ns``, if within ``max_gap_s`` of it; else None."""
        history = list(self._history)          # (a copy: the IMU callback may be appending), by stamp
        if not history:
            return None
        i = bisect.bisect_left(history, stamp_ns, key=lambda h: h[0])
        nearest = min(history[max(i - 1, 0):i + 1], key=lambda h: abs(h[0] - stamp_ns))
        return nearest if abs(nearest[0] - stamp_ns) <= max_gap_s * 1e9 else None

    def orientation_at(self, stamp_ns: int, max_gap_s: float = 0.02):
        """(orientation, epoch) of the sample nearest ``stamp_ns`` among the recent ones, if
        within ``max_gap_s`` of it (a frame's IMU may arrive before or after it); else None."""
        found = self._nearest(stamp_ns, max_gap_s)
        if found is None or found[2] is None:
            return None
        return _orthonormal(found[2]), found[1]

    def gravity_at(self, stamp_ns: int, max_gap_s: float = 0.02) -> np.ndarray:
        """Unit gravity ("down") in the IMU frame at ``stamp_ns``: the newest estimate turned
        back by the gyroscope to the recent sample nearest ``stamp_ns`` (within ``max_gap_s``;
        without a gyroscope between them, or more than ``tau_s`` before the newest sample, the
        estimate that sample left: the gyroscope's drift over a longer turn back costs more
        than the newer samples' averaging gains). A frame detected after later IMU samples
        arrived gets gravity as it was when the frame was taken, not as the camera has turned
        since. Without such a sample: :meth:`gravity`."""
        found = self._nearest(stamp_ns, max_gap_s)
        if found is None:
            return self.gravity()
        sample_ns, epoch, orientation, force = found
        if (orientation is not None and self._orientation is not None and epoch == self.epoch
                and (self._stamp_ns - sample_ns) * 1e-9 <= self.tau_s):
            # a fixed direction in the integration frame, seen from the body at the sample
            force = _orthonormal(orientation).T @ (_orthonormal(self._orientation) @ self._force)
        return -force / np.linalg.norm(force)

    @property
    def last_stamp_ns(self):
        """Stamp of the last accepted sample (None before any)."""
        return self._stamp_ns

    @property
    def ready(self) -> bool:
        return self._force is not None

    def gravity(self) -> np.ndarray:
        """Unit gravity ("down") in the IMU frame. Raises RuntimeError before any sample."""
        if self._force is None:
            raise RuntimeError('no IMU sample yet')
        return -self._force / np.linalg.norm(self._force)

    def age_s(self, stamp_ns: int) -> float:
        """Seconds the last sample is older than ``stamp_ns``: 0 when it is newer (a frame the
        detector took late, whose gravity the recent samples still hold), inf before any."""
        return np.inf if self._stamp_ns is None else max(stamp_ns - self._stamp_ns, 0) * 1e-9
