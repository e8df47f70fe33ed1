"""Gravity from an IMU: a complementary filter of accelerometer and gyroscope.

At rest the accelerometer reads +9.81 m/s^2 along "up"; while the camera moves, the
reading adds the camera's own acceleration, which averages out over a second or so. A
plain low-pass of the accelerometer therefore lags every rotation of the camera (several
degrees for a handheld camera). Here the estimate is rotated with the gyroscope between
samples (in the camera frame a fixed direction v moves as dv/dt = -w x v) and pulled
towards the accelerometer with time constant ``tau_s``. Without gyroscope readings it
degrades to the low-pass. Everything is in the IMU's frame (the camera optical frame, or
rotated into it by the caller).
"""
from __future__ import annotations

import numpy as np

__all__ = ['GravityFilter']


def _rotate(v: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rotate v by the rotation vector (Rodrigues)."""
    angle = np.linalg.norm(rotvec)
    if angle < 1e-12:
        return v
    k = rotvec / angle
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * (k @ v) * (1 - np.cos(angle))


class GravityFilter:

    def __init__(self, tau_s: float = 1.0, max_gap_s: float = 1.0):
        if tau_s <= 0:
            raise ValueError('tau_s must be > 0')
        self.tau_s = float(tau_s)
        self.max_gap_s = float(max_gap_s)
        self._force = None
        self._stamp_ns = None
        self.samples = 0
        self.rejected = 0

    def add(self, stamp_ns: int, specific_force, angular_velocity=None) -> bool:
        """Add one IMU sample: specific force (m/s^2) and, optionally, angular velocity
        (rad/s). Returns False (and ignores it) when invalid: non-finite, far from 1 g in
        magnitude, or older than the last accepted sample."""
        f = np.asarray(specific_force, dtype=np.float64).reshape(-1)
        norm = np.linalg.norm(f) if f.size == 3 else np.nan
        if not np.isfinite(norm) or not 4.0 < norm < 20.0:
            self.rejected += 1
            return False
        if self._stamp_ns is not None and stamp_ns < self._stamp_ns:
            self.rejected += 1
            return False
        if self._force is None or (stamp_ns - self._stamp_ns) * 1e-9 > self.max_gap_s:
            self._force = f.copy()
        else:
            dt = (stamp_ns - self._stamp_ns) * 1e-9
            if angular_velocity is not None:
                w = np.asarray(angular_velocity, dtype=np.float64).reshape(3)
                if np.all(np.isfinite(w)):
                    self._force = _rotate(self._force, -w * dt)
            alpha = 1.0 - np.exp(-dt / self.tau_s)
            self._force += alpha * (f - self._force)
        self._stamp_ns = int(stamp_ns)
        self.samples += 1
        return True

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
        """Seconds between the last sample and ``stamp_ns`` (inf before any sample)."""
        return np.inf if self._stamp_ns is None else abs(stamp_ns - self._stamp_ns) * 1e-9
