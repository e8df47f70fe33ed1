"""Camera trajectories through a Room, and the IMU readings along them.

Styles (paper: CA-1M is handheld video, ScanNet++ DSLR captures are scattered):

- ``handheld``: a smooth walk around the room (about 0.35 m/s) at eye height, looking
  towards a slowly wandering point in the room, with pitch/roll jitter of a hand;
- ``sparse``: scattered viewpoints (DSLR-like), random positions and viewing directions,
  in random order; the photographer holds the camera still for a moment at each and carries
  it between them (its IMU sees the walk and the turns between photos);
- ``orbit``: a circle around the room's center, looking at the center;
- ``robot``: a level camera on a wheeled base (0.3-0.9 m up) that turns in place
  (25-45 deg/s, now and then a full spin) and drives straight (0.2-0.5 m/s) between free
  places, looking ahead; no pitch or roll (:class:`RobotPath`, whose base pose the wheel
  odometry follows);
- ``outward``: a handheld walk on a small loop near the room's centre, looking out at the
  walls and the furniture along them (the other direction from ``handheld``'s look across
  the room: a second session, or relocalization queries from the other side of the objects).

Poses are camera-to-map: ``rotation`` maps the camera optical frame (x right, y down,
z forward) to the map frame (z up). Everything is deterministic for a seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from rfm_core.sim.room import Room

__all__ = ['CAPTURE_STYLES', 'Trajectory', 'ImuSamples', 'RobotPath', 'make_trajectory', 'imu_samples',
           'wheel_odometry', 'look_rotation']

CAPTURE_STYLES = ('handheld', 'sparse', 'orbit', 'robot', 'outward')
GRAVITY = 9.80665


@dataclass
class Trajectory:
    style: str
    times: np.ndarray        #: (F,) seconds from the start
    rotations: np.ndarray    #: (F, 3, 3) camera-to-map
    positions: np.ndarray    #: (F, 3) camera centers in the map frame (m)
    smooth: bool             #: whether the frames sample a continuous path (a video, not photos)
    #: t (s, array) -> (rotations, positions) of the continuous path (for sparse views, the walk
    #: from one to the next)
    pose_fn: Callable | None = field(default=None, repr=False, compare=False)
    path: 'RobotPath | None' = field(default=None, repr=False, compare=False)    #: a robot's moves

    def __len__(self) -> int:
        return len(self.times)


@dataclass
class ImuSamples:
    times: np.ndarray             #: (S,) seconds
    linear_acceleration: np.ndarray   #: (S, 3) specific force in the camera optical frame (m/s^2)
    angular_velocity: np.ndarray      #: (S, 3) in the camera optical frame (rad/s)


def look_rotation(forward, roll: float = 0.0) -> np.ndarray:
    """Camera-to-map rotation of an optical frame looking along ``forward`` with a roll (rad)."""
    f = np.asarray(forward, dtype=np.float64)
    f = f / np.linalg.norm(f)
    right = np.cross(f, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, f], axis=1)


class _HandheldPath:
    """Continuous handheld motion, so that the IMU can be sampled at any time."""

    def __init__(self, room: Room, rng, speed: float = 0.35, height=None):
        w, d = room.size[:2]
        self.center = np.array([w / 2, d / 2])
        self.reach = 0.7 * np.array([w / 2 - 0.3, d / 2 - 0.3])   # look across the room
        scale = rng.uniform(0.45, 1.0)
        self.radii = scale * np.array([max(w / 2 - 1.2, 0.4), max(d / 2 - 1.2, 0.4)])
        self.perimeter = np.pi * (3 * self.radii.sum() - np.sqrt(
            (3 * self.radii[0] + self.radii[1]) * (self.radii[0] + 3 * self.radii[1])))
        self.omega = speed / (self.perimeter / (2 * np.pi))
        self.phase = rng.uniform(0, 2 * np.pi)
        self.direction = rng.choice([-1.0, 1.0])
        self.height = rng.uniform(1.45, 1.65)
        self.noise_rng_seed = int(rng.integers(2**31))
        nrng = np.random.default_rng(self.noise_rng_seed)
        self.wobble = [nrng.uniform(0, 2 * np.pi, 3) for _ in range(8)]
        self.target_offset = nrng.uniform(0.3, 0.7)
        if height is not None:                    # another height range (from a stream of its own)
            self.height = np.random.default_rng([self.noise_rng_seed, 1]).uniform(*height)
        self.outward = False

    def look_out(self, room: Room) -> '_HandheldPath':
        """This walk on a loop near the room's centre, looking out (``outward``)."""
        orng = np.random.default_rng([self.noise_rng_seed, 2])
        self.radii = orng.uniform(0.3, 0.7) * np.minimum(self.radii, 1.0)
        self.perimeter = 2 * np.pi * self.radii.mean()
        self.omega = 0.25 / self.radii.mean()       # a slow walk: 0.25 m/s
        self.reach = np.array([room.size[0] / 2 - 0.3, room.size[1] / 2 - 0.3])
        self.outward = True
        return self

    def _wave(self, i, t, amplitude, freqs=(0.11, 0.23, 0.47)):
        return amplitude * sum(np.sin(2 * np.pi * f * t + p)
                               for f, p in zip(freqs, self.wobble[i])) / len(freqs)

    def pose(self, t):
        t = np.asarray(t, dtype=np.float64)
        a = self.phase + self.direction * self.omega * t
        xy = self.center + self.radii * np.stack([np.cos(a), np.sin(a)], -1) * (
            1 + self._wave(0, t, 0.15))[..., None]
        z = self.height + self._wave(1, t, 0.05)
        position = np.concatenate([xy, z[..., None]], -1)
        # Look across the room: towards a point ahead of and opposite to the walker; or out, at the
        # walls beyond the walker.
        ahead = a + (self.direction * (self._wave(2, t, 0.6) + 0.4 * (self.target_offset - 0.5)) if self.outward
                     else self.direction * (np.pi * self.target_offset + self._wave(2, t, 0.6)))
        target_xy = self.center + self.reach * np.stack([np.cos(ahead), np.sin(ahead)], -1)
        target_z = 0.6 + self._wave(3, t, 0.3)
        forward = np.concatenate([target_xy, target_z[..., None]], -1) - position
        roll = self._wave(4, t, np.radians(3.0), freqs=(0.7, 1.3, 2.1))
        pitch_jitter = self._wave(5, t, np.radians(2.0), freqs=(0.9, 1.7, 2.9))
        forward = np.atleast_2d(forward)
        forward = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
        forward[:, 2] += np.atleast_1d(pitch_jitter)
        rotations = np.stack([look_rotation(f, r) for f, r in zip(forward, np.atleast_1d(roll))])
        return rotations, np.atleast_2d(position)


def _ease(u):
    """Smoothstep: 0 -> 1 with zero rate at both ends (finite acceleration, for the IMU)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


class RobotPath:
    """A wheeled base's moves (see the module): turns in place and straight drives, each
    eased in and out, planned through the room's free space with ``clearance`` from every
    object at the base's and the camera's height. The camera sits ``MOUNT_X`` ahead of the
    base's centre at ``height``, level, looking ahead. :meth:`base` is the base's planar pose
    (the ground truth the wheel odometry drifts from); :meth:`pose` the camera's."""

    MOUNT_X = 0.1                         #: camera ahead of the base's centre (m)
    SPEED = (0.2, 0.5)                    #: peak drive speed (m/s)
    TURN_RATE = (25.0, 45.0)              #: peak turn rate (deg/s)

    def __init__(self, room: Room, rng, duration: float, height=(0.3, 0.9), clearance: float = 0.35):
        self.height = float(rng.uniform(*height))
        self.room = room
        xy = None
        for self.clearance in (clearance, clearance / 2, clearance / 4):     # closer in a crowded room
            xy = next((p for p in (rng.uniform(0.8, room.size[:2] - 0.8) for _ in range(500)) if self._free(p)), None)
            if xy is not None:
                break
        if xy is None:
            raise RuntimeError('no free place for a robot in this room')
        heading = float(rng.uniform(-np.pi, np.pi))
        self.moves = []                   # (t0, t1, xy0, heading0, xy1, heading1)
        t = 0.0
        while t < duration:
            if rng.random() < 0.12:                                  # a full spin, now and then
                target, length = heading + rng.choice([-1.0, 1.0]) * 2 * np.pi, 0.0
            else:
                target, length = self._direction(rng, xy, heading)
            rate = np.radians(rng.uniform(*self.TURN_RATE))
            turn_s = 1.5 * abs(target - heading) / rate               # eased: the peak rate is 1.5x the mean
            if turn_s > 0:
                self.moves.append((t, t + turn_s, xy, heading, xy, target))
                t += turn_s
            heading = float(target)                                   # unwrapped: the base turns continuously
            if length > 0:
                end = xy + length * np.array([np.cos(heading), np.sin(heading)])
                drive_s = 1.5 * length / rng.uniform(*self.SPEED)
                self.moves.append((t, t + drive_s, xy, heading, end, heading))
                t, xy = t + drive_s, end
            pause = rng.uniform(0.0, 0.6)
            self.moves.append((t, t + pause, xy, heading, xy, heading))
            t += pause
        self._starts = np.array([m[0] for m in self.moves])

    def _free(self, xy) -> bool:
        return not any(self.room.contains_camera((xy[0], xy[1], z), margin=self.clearance)
                       for z in (max(self.clearance, 0.3), max(self.height, self.clearance)))

    def _direction(self, rng, xy, heading):
        """A new heading and a drive along it through free space (the longest found in a few
        tries, 0.4-2 m; none: turn and stay)."""
        best = (heading + rng.uniform(-np.pi, np.pi), 0.0)
        for _ in range(24):
            target = heading + rng.uniform(-np.pi, np.pi)
            direction = np.array([np.cos(target), np.sin(target)])
            want = rng.uniform(0.4, 2.0)
            length = 0.0
            for step in np.arange(0.1, want + 1e-9, 0.1):
                if not self._free(xy + step * direction):
                    break
                length = step
            if length > best[1]:
                best = (target, length)
            if length >= want - 1e-9:
                break
        return best if best[1] >= 0.4 else (best[0], 0.0)

    def base(self, t):
        """(x, y, heading) of the base's centre at times ``t`` (arrays of (T,))."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        i = np.clip(np.searchsorted(self._starts, t, side='right') - 1, 0, len(self.moves) - 1)
        out = np.zeros((len(t), 3))
        for k in np.unique(i):
            t0, t1, xy0, h0, xy1, h1 = self.moves[k]
            u = _ease((t[i == k] - t0) / max(t1 - t0, 1e-9))
            out[i == k, :2] = np.asarray(xy0) + u[:, None] * (np.asarray(xy1) - np.asarray(xy0))
            out[i == k, 2] = h0 + u * (h1 - h0)
        return out

    def pose(self, t):
        base = self.base(t)
        forward = np.stack([np.cos(base[:, 2]), np.sin(base[:, 2]), np.zeros(len(base))], -1)
        positions = np.c_[base[:, :2] + self.MOUNT_X * forward[:, :2], np.full(len(base), self.height)]
        return np.stack([look_rotation(f) for f in forward]), positions


def _orbit(room: Room, rng):
    w, d = room.size[:2]
    center = np.array([w / 2, d / 2, 0.6])
    radius = max(min(w, d) / 2 - 1.0, 0.5)
    phase = rng.uniform(0, 2 * np.pi)
    height = rng.uniform(1.4, 1.7)

    def pose(t, duration):
        a = phase + 2 * np.pi * np.asarray(t) / max(duration, 1e-9)
        pos = np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a),
                        np.full_like(a, height)], -1)
        rot = np.stack([look_rotation(center - p) for p in np.atleast_2d(pos)])
        return rot, np.atleast_2d(pos)
    return pose


def _photo_walk(times, rotations, positions, hold_s: float = 0.5):
    """The camera's path through sparse viewpoints: still for ``hold_s`` before and after each
    photo (a quarter of a shorter gap), carried to the next in between with a minimum-jerk
    profile (zero speed and acceleration at both ends), turned along the shortest rotation."""
    from scipy.spatial.transform import Rotation  # noqa: PLC0415

    def pose(t):
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if len(times) < 2:
            return np.repeat(rotations[:1], len(t), 0), np.repeat(positions[:1], len(t), 0)
        i = np.clip(np.searchsorted(times, t, side='right') - 1, 0, len(times) - 2)
        gap = times[i + 1] - times[i]
        hold = np.minimum(hold_s, gap / 4)
        u = np.clip((t - times[i] - hold) / (gap - 2 * hold), 0.0, 1.0)
        s = u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u)
        turn = Rotation.from_matrix(np.einsum('nji,njk->nik', rotations[i], rotations[i + 1])).as_rotvec()
        return (rotations[i] @ Rotation.from_rotvec(s[:, None] * turn).as_matrix(),
                positions[i] + s[:, None] * (positions[i + 1] - positions[i]))
    return pose


def _free_position(room: Room, rng, margin=0.8):
    for _ in range(200):
        p = np.array([rng.uniform(margin, room.size[0] - margin),
                      rng.uniform(margin, room.size[1] - margin), rng.uniform(1.2, 1.8)])
        if not room.contains_camera(p, margin=0.3):
            return p
    raise RuntimeError('no free camera position in this room')


def make_trajectory(room: Room, style: str, num_frames: int, fps: float = 30.0,
                    seed: int = 0, height=None, sparse_gap_s=(1.0, 1.0)) -> Trajectory:
    """A camera trajectory of ``num_frames`` frames through ``room``.

    Handheld, orbit and robot frames are ``1 / fps`` apart; sparse viewpoints are
    ``sparse_gap_s`` (a range: photos taken irregularly) apart. ``height``: a (min, max) range
    of the handheld or robot camera's height instead of the style's. Camera positions never
    fall inside furniture: a path that would is re-drawn.
    """
    if style not in CAPTURE_STYLES:
        raise ValueError(f'capture style must be one of {CAPTURE_STYLES}, got {style!r}')
    if num_frames < 1:
        raise ValueError('num_frames must be >= 1')
    rng = np.random.default_rng(seed)
    if style == 'sparse':
        lo, hi = sparse_gap_s
        times = (np.arange(num_frames, dtype=np.float64) if lo == hi == 1.0 else
                 np.r_[0.0, np.cumsum(np.random.default_rng([seed, 5]).uniform(lo, hi, num_frames - 1))])
        positions, rotations = [], []
        for _ in range(num_frames):
            p = _free_position(room, rng)
            target = np.array([rng.uniform(0.5, room.size[0] - 0.5),
                               rng.uniform(0.5, room.size[1] - 0.5), rng.uniform(0.2, 1.0)])
            if np.linalg.norm(target[:2] - p[:2]) < 1.0:
                target[:2] = room.size[:2] - p[:2]        # look across the room
            positions.append(p)
            rotations.append(look_rotation(target - p, rng.normal(0, np.radians(2))))
        rotations, positions = np.array(rotations), np.array(positions)
        return Trajectory(style, times, rotations, positions, smooth=False,
                          pose_fn=_photo_walk(times, rotations, positions))

    times = np.arange(num_frames) / float(fps)
    if style == 'orbit':
        pose = _orbit(room, rng)
        duration = max(times[-1], 20.0)
        rotations, positions = pose(times, duration)
        return Trajectory(style, times, rotations, positions, smooth=True,
                          pose_fn=lambda t: pose(t, duration))
    if style == 'robot':
        path = RobotPath(room, rng, times[-1] + 1.0, height=height or (0.3, 0.9))
        rotations, positions = path.pose(times)
        return Trajectory(style, times, rotations, positions, smooth=True, pose_fn=path.pose, path=path)
    # Keep at least 0.6 m from furniture if some path allows it, else at least 0.15 m.
    candidates = []
    for _attempt in range(30):
        path = _HandheldPath(room, rng, speed=0.35, height=height)
        if style == 'outward':
            path.look_out(room)
        rotations, positions = path.pose(times)
        clearance = next((m for m in (0.6, 0.15) if not any(
            room.contains_camera(p, margin=m) for p in positions)), 0.0)
        candidates.append((clearance, path, rotations, positions))
        if clearance >= 0.6:
            break
    _, path, rotations, positions = max(candidates, key=lambda c: c[0])
    return Trajectory(style, times, rotations, positions, smooth=True, pose_fn=path.pose)


def imu_samples(traj: Trajectory, rate_hz: float, seed: int = 0,
                accel_sigma: float = 0.02, gyro_sigma: float = 0.002, gyro_bias: float = 0.0,
                accel_bias: float = 0.0) -> ImuSamples:
    """IMU readings in the camera optical frame at ``rate_hz`` over the trajectory.

    Specific force f = R^T (a - g) with g = (0, 0, -9.80665): at rest it reads +9.81 along
    "up". Acceleration and angular rate come from central differences of the continuous path
    (for sparse views, the walk between them). ``gyro_bias`` (rad/s) and ``accel_bias``
    (m/s^2): constant biases in random directions.
    """
    rng = np.random.default_rng(seed)
    end = traj.times[-1] if len(traj) > 1 else 0.0
    times = np.arange(0.0, end + 1e-9, 1.0 / rate_hz)
    g = np.array([0.0, 0.0, -GRAVITY])
    if traj.pose_fn is None:
        raise ValueError('IMU readings need the continuous path (Trajectory.pose_fn)')
    dt = 1e-3
    r0, p0 = traj.pose_fn(times)
    r_prev, p_prev = traj.pose_fn(times - dt)
    r_next, p_next = traj.pose_fn(times + dt)
    accel_world = (p_next - 2 * p0 + p_prev) / dt ** 2
    dr = np.einsum('nji,njk->nik', r0, (r_next - r_prev) / (2 * dt))   # R^T dR/dt
    omega = np.stack([dr[:, 2, 1] - dr[:, 1, 2], dr[:, 0, 2] - dr[:, 2, 0],
                      dr[:, 1, 0] - dr[:, 0, 1]], -1) / 2
    force = np.einsum('nji,nj->ni', r0, accel_world - g)
    force += rng.normal(0, accel_sigma, force.shape)
    omega = omega + rng.normal(0, gyro_sigma, omega.shape)
    if gyro_bias > 0 or accel_bias > 0:                 # constant biases, in random directions
        bias = np.random.default_rng([seed, 3]).normal(size=(2, 3))
        bias /= np.linalg.norm(bias, axis=1, keepdims=True)
        force = force + accel_bias * bias[0]
        omega = omega + gyro_bias * bias[1]
    return ImuSamples(times, force, omega)


def wheel_odometry(path: RobotPath, times, seed: int = 0, scale_error: float = 0.0, turn_error: float = 0.0,
                   yaw_bias_dps: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A differential drive's odometry along ``path`` at ``times`` (s): (T, 3) poses (x, y,
    heading) in the odometry frame (the base's first pose) and (T, 2) velocities (forward m/s,
    turn rad/s). Each step's distance and turn are the base's true ones scaled by errors drawn
    once (standard deviations ``scale_error``, ``turn_error``), plus a constant yaw drift of
    ``yaw_bias_dps`` (either sign), integrated: the drift grows with the distance and the turns."""
    rng = np.random.default_rng([seed, 11])
    scale, turn = 1.0 + rng.normal(0.0, scale_error), 1.0 + rng.normal(0.0, turn_error)
    bias = np.radians(yaw_bias_dps) * rng.choice([-1.0, 1.0])
    t = np.asarray(times, dtype=np.float64)
    base = path.base(t)
    out = np.zeros((len(t), 3))
    velocity = np.zeros((len(t), 2))
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        c, s = np.cos(base[k - 1, 2]), np.sin(base[k - 1, 2])
        step = base[k, :2] - base[k - 1, :2]
        forward = (c * step[0] + s * step[1]) * scale                  # along the base's heading
        dtheta = (base[k, 2] - base[k - 1, 2]) * turn + bias * dt
        mid = out[k - 1, 2] + dtheta / 2
        out[k] = out[k - 1] + (forward * np.cos(mid), forward * np.sin(mid), dtheta)
        velocity[k] = (forward / dt, dtheta / dt) if dt > 0 else velocity[k - 1]
    return out, velocity
