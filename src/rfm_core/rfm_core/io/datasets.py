"""RGB-D dataset folders as rosbag2 bags ``rfm run --bag`` takes (``rfm convert``).

Two layouts, one reader (:func:`read_folder`):

- **TUM RGB-D** (the benchmark's sequence folders as downloaded): ``rgb.txt`` and
  ``depth.txt`` list ``timestamp path`` lines (``#`` comments), colour PNGs, depth PNGs of
  16 bits at 5000 per metre, ``accelerometer.txt`` (``timestamp ax ay az``, m/s^2, the
  Kinect's accelerometer) and ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``: the
  colour camera's optical frame in the motion-capture frame). The intrinsics are TUM's
  published ones for the ``freiburg1/2/3`` camera named in the folder (the lens distortion
  of freiburg1 and 2 is not modelled), else its default 525/525/319.5/239.5.
- **Generic**: the same files plus ``camera.yaml`` (``fx``, ``fy``, ``cx``, ``cy``,
  ``depth_scale``: depth units per metre, e.g. 1000 for millimetres; optional
  ``accel_axes``), an optional ``imu.txt`` (``timestamp ax ay az [wx wy wz]`` in the camera
  optical frame: accelerometer in m/s^2, gyroscope in rad/s) in place of the accelerometer
  file, and an optional ``groundtruth.txt``. ScanNet, ScanNet++ and ARKitScenes exports
  (a colour and a depth image per frame, intrinsics, per-frame poses) map onto it with a
  few lines (README, "Running on your own data").

Each colour image is paired with the depth image nearest in time (within
``max_difference_s``, as TUM's ``associate.py``). The IMU is written in the camera optical
frame (x right, y down, z forward): ``accel_axes`` names, per optical axis, the file's axis
that measures it (``'x,y,z'``: the file's axes are the optical frame's; ``'-y,x,z'``:
optical x is the file's -y, ...). An accelerometer without a gyroscope is marked so
(REP 145: ``angular_velocity_covariance[0] = -1``); gravity then comes from the
accelerometer alone. Ground truth goes on ``/ground_truth/camera_pose``, levelled where the
accelerometer allows: evaluation aligns in 4 DoF (yaw and translation) about gravity, so a
motion-capture frame whose z is not up is turned, once for the whole sequence, to the
direction the accelerometer reads as up (:func:`level_ground_truth`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rfm_core.geometry import matrix_from_quaternion
from rfm_core.observations import CameraIntrinsics
from rfm_core.transforms import interpolate

__all__ = ['RgbdFolder', 'read_folder', 'write_bag', 'level_ground_truth', 'parse_axes', 'TUM_INTRINSICS']

#: TUM RGB-D's published colour intrinsics (fx, fy, cx, cy) per camera, and its default
TUM_INTRINSICS = {'freiburg1': (517.3, 516.5, 318.6, 255.3), 'freiburg2': (520.9, 521.0, 325.1, 249.7),
                  'freiburg3': (535.4, 539.2, 320.1, 247.6), 'default': (525.0, 525.0, 319.5, 239.5)}
TUM_DEPTH_SCALE = 5000.0        #: TUM depth PNG units per metre


@dataclass
class RgbdFolder:
    """A dataset folder read: colour/depth pairs, intrinsics, IMU and ground truth."""

    root: Path
    layout: str                                   #: 'tum' or 'generic'
    frames: list                                  #: [(colour stamp_ns, colour path, depth stamp_ns, depth path)]
    intrinsics: tuple                             #: (fx, fy, cx, cy)
    depth_scale: float                            #: depth units per metre
    imu_stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   #: (N,) ns
    imu: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))   #: (N, 6) accel, gyro (NaN: none); optical
    ground_truth: list = field(default_factory=list)   #: [(frame stamp_ns, 4x4 camera-to-world)]
    skipped: int = 0                              #: colour images without depth near enough in time


def _ns(seconds: str) -> int:
    whole, _, frac = seconds.strip().partition('.')
    return int(whole) * 1_000_000_000 + int((frac + '000000000')[:9] or 0)


def _lines(path: Path) -> list:
    """Whitespace-separated fields of a text file's lines, comments and blanks skipped."""
    out = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if line and not line.startswith('#'):
            out.append((number, line.split()))
    return out


def _image_list(path: Path) -> list:
    """``timestamp path`` lines -> [(stamp_ns, absolute path)], in time order."""
    if not path.is_file():
        raise FileNotFoundError(f'{path} is missing: a dataset folder lists its images in rgb.txt and depth.txt '
                                '("timestamp path" per line)')
    out = []
    for number, fields in _lines(path):
        if len(fields) < 2:
            raise ValueError(f'{path}:{number}: expected "timestamp path", got {" ".join(fields)!r}')
        try:
            stamp = _ns(fields[0])
        except ValueError:
            raise ValueError(f'{path}:{number}: bad timestamp {fields[0]!r}') from None
        out.append((stamp, path.parent / fields[1]))
    return sorted(out)


def _table(path: Path, width: tuple) -> tuple[np.ndarray, np.ndarray]:
    """A ``timestamp value...`` table of ``width`` columns (one of them; short rows NaN-padded
    to the widest): (stamps in ns, exact from the text; the values)."""
    stamps, rows = [], []
    for number, fields in _lines(path):
        if len(fields) not in width:
            raise ValueError(f'{path}:{number}: expected {" or ".join(map(str, width))} numbers, got {len(fields)}')
        try:
            stamps.append(_ns(fields[0]))
            rows.append([float(v) for v in fields[1:]] + [np.nan] * (max(width) - len(fields)))
        except ValueError:
            raise ValueError(f'{path}:{number}: not a number in {" ".join(fields)!r}') from None
    values = np.array(rows, float).reshape(-1, max(width) - 1)
    if not np.all(np.isfinite(values[:, :min(width) - 1])):
        raise ValueError(f'{path}: non-finite values')
    order = np.argsort(np.array(stamps, np.int64), kind='stable')
    return np.array(stamps, np.int64)[order], values[order]


def parse_axes(text: str) -> np.ndarray:
    """(3, 3) R with optical = R @ file, from ``'x,y,z'``-style names (see the module)."""
    names = [t.strip().lower() for t in str(text).split(',')]
    r = np.zeros((3, 3))
    for row, name in enumerate(names):
        sign = -1.0 if name.startswith('-') else 1.0
        axis = name.lstrip('+-')
        if len(names) != 3 or axis not in ('x', 'y', 'z'):
            raise ValueError(f"accel_axes must name three axes such as 'x,y,z' or '-y,x,z', got {text!r}")
        r[row, 'xyz'.index(axis)] = sign
    if abs(abs(np.linalg.det(r)) - 1.0) > 1e-9:
        raise ValueError(f'accel_axes {text!r} repeats an axis')
    return r


def _camera_yaml(path: Path) -> dict:
    import yaml  # noqa: PLC0415

    with open(path) as f:
        cam = yaml.safe_load(f) or {}
    if not isinstance(cam, dict):
        raise ValueError(f'{path}: expected a mapping with fx, fy, cx, cy, depth_scale')
    missing = [k for k in ('fx', 'fy', 'cx', 'cy', 'depth_scale') if k not in cam]
    if missing:
        raise ValueError(f'{path}: missing {", ".join(missing)} (fx, fy, cx, cy in pixels; depth_scale: depth '
                         'units per metre, 1000 for millimetres, 5000 for TUM)')
    values = [float(cam[k]) for k in ('fx', 'fy', 'cx', 'cy', 'depth_scale')]
    if not all(np.isfinite(values)) or min(values[0], values[1], values[4]) <= 0:
        raise ValueError(f'{path}: fx, fy and depth_scale must be positive numbers')
    return cam


def read_folder(root, intrinsics=None, accel_axes: str | None = None,
                max_difference_s: float = 0.02) -> RgbdFolder:
    """A TUM RGB-D or generic dataset folder (see the module). ``intrinsics`` (fx, fy, cx,
    cy) and ``accel_axes`` override the folder's; ValueError / FileNotFoundError say what
    is wrong with it."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f'{root} is not a folder')
    cam_file = root / 'camera.yaml'
    if cam_file.is_file():
        cam = _camera_yaml(cam_file)
        layout, k = 'generic', tuple(float(cam[n]) for n in ('fx', 'fy', 'cx', 'cy'))
        scale, axes = float(cam['depth_scale']), cam.get('accel_axes', 'x,y,z')
    else:
        layout, scale, axes = 'tum', TUM_DEPTH_SCALE, 'x,y,z'
        camera = next((c for c in ('freiburg1', 'freiburg2', 'freiburg3') if c in root.resolve().name), 'default')
        k = TUM_INTRINSICS[camera]
    if intrinsics is not None:
        k = tuple(float(v) for v in intrinsics)
    rotation = parse_axes(accel_axes or axes)
    colour, depth = _image_list(root / 'rgb.txt'), _image_list(root / 'depth.txt')
    if not colour or not depth:
        raise ValueError(f'{root}: rgb.txt and depth.txt must list at least one image each')
    depth_stamps = np.array([s for s, _ in depth], np.int64)
    frames, skipped = [], 0
    for stamp, path in colour:
        j = int(np.argmin(np.abs(depth_stamps - stamp)))
        if abs(depth_stamps[j] - stamp) > max_difference_s * 1e9:
            skipped += 1
            continue
        frames.append((stamp, path, int(depth_stamps[j]), depth[j][1]))
    imu_stamps, imu = np.zeros(0, np.int64), np.zeros((0, 6))
    if (root / 'imu.txt').is_file():
        imu_stamps, imu = _table(root / 'imu.txt', (4, 7))
    elif (root / 'accelerometer.txt').is_file():
        imu_stamps, accel = _table(root / 'accelerometer.txt', (4,))
        imu = np.c_[accel, np.full((len(accel), 3), np.nan)]            # no gyroscope
    imu = np.c_[imu[:, :3] @ rotation.T, imu[:, 3:] @ rotation.T]
    truth = []
    if (root / 'groundtruth.txt').is_file():
        gt_stamps, rows = _table(root / 'groundtruth.txt', (8,))
        norms = np.linalg.norm(rows[:, 3:7], axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
        if len(bad):
            raise ValueError(f'{root / "groundtruth.txt"}: quaternion of norm {norms[bad[0]]:.4f} at '
                             f'{gt_stamps[bad[0]] * 1e-9:.6f} (expected "timestamp tx ty tz qx qy qz qw")')
        truth = _at_frames([s for s, *_ in frames], gt_stamps, rows[:, :3], rows[:, 3:7] / norms[:, None])
    return RgbdFolder(root, layout, frames, k, scale, imu_stamps, imu, truth, skipped)


def _at_frames(stamps: list, gt_stamps: np.ndarray, positions: np.ndarray, quaternions: np.ndarray,
               max_gap_s: float = 0.1) -> list:
    """Ground truth at the frames' stamps (evaluation compares poses of one stamp):
    interpolated between the two poses around each (:func:`rfm_core.transforms.interpolate`)
    where they are at most ``max_gap_s`` apart; frames outside the ground truth have none."""
    poses = np.tile(np.eye(4), (len(gt_stamps), 1, 1))
    poses[:, :3, :3] = matrix_from_quaternion(quaternions)
    poses[:, :3, 3] = positions
    out = []
    for s in stamps:
        j = int(np.searchsorted(gt_stamps, s))
        if j < len(gt_stamps) and gt_stamps[j] == s:
            out.append((s, poses[j]))
        elif 0 < j < len(gt_stamps) and (gt_stamps[j] - gt_stamps[j - 1]) * 1e-9 <= max_gap_s:
            share = (s - gt_stamps[j - 1]) / (gt_stamps[j] - gt_stamps[j - 1])
            out.append((s, interpolate(poses[j - 1], poses[j], share)))
    return out


def level_ground_truth(truth: list, imu_stamps: np.ndarray, imu: np.ndarray,
                       max_gap_s: float = 0.05) -> tuple[list, float]:
    """Ground truth turned so that its z axis is up. The accelerometer reads the camera's
    acceleration minus gravity; rotated into the ground truth's frame by the pose nearest each
    sample (within ``max_gap_s``) and averaged, it is gravity's opposite minus the camera's mean
    acceleration, which is its change of velocity over the time (from the ground truth's
    positions at both ends). Returns (poses, the turn in degrees); unchanged (0) without IMU
    samples near the poses."""
    from scipy.spatial.transform import Rotation  # noqa: PLC0415

    if len(truth) < 2 or not len(imu):
        return truth, 0.0
    stamps = np.array([s for s, _ in truth], np.int64)
    forces, times = [], []
    for ns, f in zip(imu_stamps, imu[:, :3]):
        j = int(np.argmin(np.abs(stamps - ns)))
        if abs(stamps[j] - ns) <= max_gap_s * 1e9:
            forces.append(truth[j][1][:3, :3] @ np.asarray(f, float))
            times.append(ns)
    if len(forces) < 2 or times[-1] == times[0]:
        return truth, 0.0

    def velocity(ns):              # from the two ground-truth poses around a moment
        j = int(np.clip(np.searchsorted(stamps, ns), 1, len(stamps) - 1))
        return (truth[j][1][:3, 3] - truth[j - 1][1][:3, 3]) / max((stamps[j] - stamps[j - 1]) * 1e-9, 1e-6)

    mean_accel = (velocity(times[-1]) - velocity(times[0])) / ((times[-1] - times[0]) * 1e-9)
    up = np.mean(forces, axis=0) - mean_accel
    if np.linalg.norm(up) < 1e-9:
        return truth, 0.0
    up /= np.linalg.norm(up)
    turn = Rotation.align_vectors([[0.0, 0.0, 1.0]], [up])[0].as_matrix()     # the shortest turn of up onto z
    g = np.eye(4)
    g[:3, :3] = turn
    return [(s, g @ m) for s, m in truth], float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0))))


def _read_image(path: Path) -> np.ndarray:
    from PIL import Image  # noqa: PLC0415

    if not path.is_file():
        raise FileNotFoundError(f'{path} (listed in the folder) is missing')
    with Image.open(path) as img:
        return np.asarray(img)


def write_bag(folder: RgbdFolder, out, progress=None) -> dict:
    """Write ``folder`` as a rosbag2 MCAP bag at ``out`` (must not exist) on rfm's default
    topics (rfm_core.io.topics): colour (rgb8), depth (16UC1 millimetres, or 32FC1 metres
    where the folder's scale is not a whole number of units per millimetre), both
    camera_info, ``/imu/data`` and ``/ground_truth/camera_pose``. Returns a summary."""
    from rfm_core.io.bag import BagWriter  # noqa: PLC0415
    from rfm_core.io.images import numpy_to_image  # noqa: PLC0415
    from rfm_core.io.messages import camera_info_msg, header, imu_msg, pose_stamped_msg  # noqa: PLC0415
    from rfm_core.io.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS, OPTICAL_FRAME  # noqa: PLC0415

    if not folder.frames:
        raise ValueError(f'{folder.root}: no colour image has a depth image within the time tolerance')
    first = _read_image(folder.frames[0][1])
    height, width = first.shape[:2]
    intrinsics = CameraIntrinsics(*folder.intrinsics, width, height)
    truth, turned = level_ground_truth(folder.ground_truth, folder.imu_stamps, folder.imu)
    events = [(s, 0, i) for i, (s, *_) in enumerate(folder.frames)]
    events += [(int(t), 1, i) for i, t in enumerate(folder.imu_stamps)]
    events += [(s, 2, i) for i, (s, _) in enumerate(truth)]
    events.sort()
    counts = {'frames': 0, 'imu': 0, 'ground_truth': 0}
    millimetres = float(folder.depth_scale / 1000.0).is_integer()
    with BagWriter(out) as bag:
        make = bag.make
        bag.set_metadata('rfm.convert.source', f'{folder.layout}: {folder.root}')
        for key in ('color', 'depth'):
            bag.add_topic(CAMERA_TOPICS[key], 'sensor_msgs/msg/Image')
            bag.add_topic(CAMERA_TOPICS[f'{key}_info'], 'sensor_msgs/msg/CameraInfo')
        if len(folder.imu):
            bag.add_topic(CAMERA_TOPICS['imu'], 'sensor_msgs/msg/Imu', reliable=False)
        if truth:
            bag.add_topic(GROUND_TRUTH_TOPICS['gt_pose'], 'geometry_msgs/msg/PoseStamped')
        for stamp, kind, i in events:
            if kind == 1:
                row = folder.imu[i]
                gyro = row[3:6] if np.all(np.isfinite(row[3:6])) else None
                bag.write(CAMERA_TOPICS['imu'], stamp, imu_msg(row[:3], gyro, stamp, OPTICAL_FRAME, make=make))
                counts['imu'] += 1
                continue
            if kind == 2:
                bag.write(GROUND_TRUTH_TOPICS['gt_pose'], stamp, pose_stamped_msg(truth[i][1], stamp, 'map', make))
                counts['ground_truth'] += 1
                continue
            c_stamp, c_path, d_stamp, d_path = folder.frames[i]
            rgb = _read_image(c_path)
            depth = _read_image(d_path)
            if rgb.ndim == 2:
                rgb = np.repeat(rgb[..., None], 3, axis=2)
            rgb = np.ascontiguousarray(rgb[..., :3]).astype(np.uint8)
            if rgb.shape[:2] != (height, width) or depth.shape[:2] != (height, width) or depth.ndim != 2:
                raise ValueError(f'{c_path} / {d_path}: images of {rgb.shape[:2]} and {depth.shape} pixels; every '
                                 f'colour and depth image must be {width}x{height} (depth registered to colour)')
            if millimetres:
                depth_px = np.rint(np.asarray(depth, np.float64) / (folder.depth_scale / 1000.0))
                depth_msg = numpy_to_image(np.clip(depth_px, 0, 65535).astype(np.uint16), '16UC1',
                                           header(make, d_stamp, OPTICAL_FRAME), make=make)
            else:
                metres = np.where(depth > 0, np.asarray(depth, np.float32) / np.float32(folder.depth_scale), np.nan)
                depth_msg = numpy_to_image(metres.astype(np.float32), '32FC1', header(make, d_stamp, OPTICAL_FRAME),
                                           make=make)
            bag.write(CAMERA_TOPICS['color'], c_stamp,
                      numpy_to_image(rgb, 'rgb8', header(make, c_stamp, OPTICAL_FRAME), make=make))
            bag.write(CAMERA_TOPICS['color_info'], c_stamp, camera_info_msg(intrinsics, c_stamp, OPTICAL_FRAME, make))
            bag.write(CAMERA_TOPICS['depth'], d_stamp, depth_msg)
            bag.write(CAMERA_TOPICS['depth_info'], d_stamp, camera_info_msg(intrinsics, d_stamp, OPTICAL_FRAME, make))
            counts['frames'] += 1
            if progress is not None:
                progress(counts['frames'], len(folder.frames))
    return {**counts, 'skipped': folder.skipped, 'levelled_deg': turned, 'width': width, 'height': height,
            'layout': folder.layout, 'gyroscope': bool(len(folder.imu)) and bool(np.all(np.isfinite(folder.imu[:, 3])))}
