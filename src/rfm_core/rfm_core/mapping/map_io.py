"""Map files: versioned, self-describing, written atomically, validated on load.

A map file is a NumPy ``.npz`` archive (no pickles) holding a JSON header (format name,
version, counts, and the mapper's whole configuration, so that whoever loads the map
rebuilds its tracks as the mapper that made it did) and flat arrays: every keyframe with its
detections (boxes, scores, labels, embeddings, 2D boxes, gravity, intrinsics, stamp, frame
id), every edge with its verified object and corner matches, the keyframe poses, and every
localized frame (its pose relative to a keyframe: the full-rate trajectory) and where each
keyframe came from (the matcher session and its id there), and the keyframes culled from the
map (which kept keyframe carries each, and the views they add to objects). Object tracks
are derived data and are rebuilt on load. Files written before the configuration and the
frames were stored load with the loading mapper's configuration and no frames.

The frame log grows with every frame for as long as the camera runs. A self-contained map
file holds it; the map a node autosaves (``save_map(..., frames_beside=True)``) keeps it in a
file beside it instead, ``<map file>.<token>.frames`` (a 16-byte head, then
:data:`~rfm_core.mapping.frame_log.ROW` records), to which each autosave appends the frames
logged since the last one: an autosave costs what the map holds, not how long the run has
been. The map file names its frame file and the number of rows that belong to it; rows
appended after that (a save that failed half way) are ignored.

Writing goes to a temporary file in the same directory, is flushed to disk, then renamed
over the target: a crash leaves either the old file or the new one, never half of one.
Loading checks everything before touching the mapper: a corrupt or wrong-version file
raises :class:`MapFileError` with the reason and the current map stays as it was.
"""
from __future__ import annotations

import io
import json
import os
import re
import secrets
import tempfile
import zipfile
from glob import escape as glob_escape
from pathlib import Path

import numpy as np

from rfm_core.geometry import Pose4
from rfm_core.mapping.frame_log import ROW, FrameLog
from rfm_core.mapping.culling import Merged
from rfm_core.mapping.mapper import Mapper, MapperConfig
from rfm_core.observations import EdgeRecord
from rfm_core.observations import CameraIntrinsics, FrameObservations

__all__ = ['FORMAT', 'VERSION', 'MapFileError', 'save_map', 'load_map', 'read_map']

FORMAT = 'rfm-map'
VERSION = 1
#: a map file's arrays inflate to at most this many times the file's size, plus
#: :data:`INFLATION_ALLOWANCE` bytes (maps inflate about 1.3 times: floats barely compress);
#: more is a compression bomb, refused before anything is inflated
MAX_INFLATION = 20
INFLATION_ALLOWANCE = 64 * 2 ** 20
#: keyframe ids and stamps a map may hold: what rfm_msgs carry (uint64), within int64 arrays
MAX_ID = 2 ** 62
#: header fields that count something
_HEADER_COUNTS = ('keyframes', 'edges', 'registered', 'frames', 'revision')
#: arrays where NaN means "not measured"
_UNMEASURED = ('kf_camera_height',)
#: header fields that list strings
_HEADER_STRINGS = ('kf_frame_ids', 'kf_backends', 'det_labels')
#: a frame file's head: this, then its 8-byte token (also in its name)
_FRAMES_MAGIC = b'RFMFRM01'
_FRAMES_HEAD = 16
_FRAMES_NAME = re.compile(r'[^/\\]+\.([0-9a-f]{16})\.frames')


class MapFileError(ValueError):
    """A map file that cannot be used; the message says why."""


def _keyframe_arrays(mapper: Mapper) -> dict:
    ids = sorted(mapper.keyframes)
    frames = [mapper.keyframes[k] for k in ids]
    counts = np.array([len(f) for f in frames], np.int64)
    dims = {f.embeddings.shape[1] for f in frames if len(f)}
    dim = dims.pop() if len(dims) == 1 else 0
    def cat(get, width, dtype):
        parts = [np.asarray(get(f), dtype).reshape(len(f), *width) for f in frames]
        return np.concatenate(parts) if parts else np.zeros((0, *width), dtype)
    intr = np.array([[f.intrinsics.width, f.intrinsics.height, f.intrinsics.fx, f.intrinsics.fy,
                      f.intrinsics.cx, f.intrinsics.cy] if f.intrinsics is not None else [0] * 6
                     for f in frames], float).reshape(-1, 6)
    return {
        'kf_ids': np.array(ids, np.int64), 'kf_counts': counts,
        'kf_stamps': np.array([f.stamp_ns for f in frames], np.int64),
        'kf_gravity': np.array([f.gravity_cam for f in frames], float).reshape(-1, 3),
        'kf_intrinsics': intr,
        'det_boxes': cat(lambda f: f.boxes, (7,), np.float64),
        'det_scores': cat(lambda f: f.scores, (), np.float32),
        'det_embeddings': cat(lambda f: f.embeddings if dim else np.zeros((len(f), 0)), (dim,), np.float32),
        'det_boxes_2d': cat(lambda f: f.boxes_2d, (4,), np.float32),
        # the map's boxes (FrameObservations.full_boxes) of the keyframes that have them
        'kf_full': np.array([f.full_boxes is not None for f in frames], bool),
        'det_full_boxes': cat(lambda f: f.map_boxes, (7,), np.float64),
        # FrameObservations.camera_height (NaN: not measured)
        'kf_camera_height': np.array([f.camera_height for f in frames], float),
        # FrameObservations.walls: kf_wall_counts per keyframe, their rows in kf_walls
        'kf_wall_counts': np.array([len(f.walls) for f in frames], np.int64),
        'kf_walls': (np.concatenate([f.walls for f in frames]) if frames else np.zeros((0, 3))).reshape(-1, 3),
        # FrameObservations.cloud: kf_cloud_counts points per keyframe, their rows in kf_clouds
        'kf_cloud_counts': np.array([len(f.cloud) for f in frames], np.int64),
        'kf_clouds': (np.concatenate([f.cloud for f in frames]) if frames else np.zeros((0, 3))).astype(np.float32)
        .reshape(-1, 3),
        # where each keyframe came from: (view-graph session, its id there); (0, 0) unknown
        'kf_origin': np.array([mapper.origins.get(k, (0, 0)) for k in ids], np.uint64).reshape(-1, 2),
    }, {'kf_frame_ids': [f.frame_id for f in frames],
        'kf_backends': [f.backend for f in frames],
        'det_labels': [lab for f in frames for lab in (f.labels if len(f.labels) == len(f) else [''] * len(f))]}


def _edge_arrays(mapper: Mapper) -> dict:
    edges = mapper.measurements()
    active = {id(e) for e in mapper.active_edges()}
    return {
        'edge_ids': np.array([[e.source, e.target] for e in edges], np.int64).reshape(-1, 2),
        'edge_poses': np.array([[e.pose.yaw, *e.pose.t] for e in edges], float).reshape(-1, 4),
        'edge_scores': np.array([e.score for e in edges], float),
        'edge_active': np.array([id(e) in active for e in edges], bool),
        'edge_inlier_counts': np.array([len(e.inliers) for e in edges], np.int64),
        'edge_inliers': (np.concatenate([e.inliers for e in edges]).astype(np.int64)
                         if edges else np.zeros((0, 2), np.int64)).reshape(-1, 2),
        'edge_inlier_scores': (np.concatenate([e.scores for e in edges]).astype(np.float32)
                               if edges else np.zeros(0, np.float32)),
        'edge_corner_counts': np.array([len(e.corner_inliers) for e in edges], np.int64),
        'edge_corners': (np.concatenate([np.asarray(e.corner_inliers, float).reshape(-1, 5) for e in edges])
                         if edges else np.zeros((0, 5))).reshape(-1, 5),
    }


def _culled_arrays(mapper: Mapper) -> dict:
    """Keyframes culled from the map (each carried by a kept keyframe) and the views they add."""
    ids = sorted(mapper.merged)
    merged = [mapper.merged[k] for k in ids]
    carried = sorted(mapper.carried)
    return {
        'merged_ids': np.array(ids, np.int64),
        'merged_into': np.array([m.into for m in merged], np.int64),
        'merged_poses': np.array([[m.pose.yaw, *m.pose.t] for m in merged], float).reshape(-1, 4),
        'merged_stamps': np.array([m.stamp_ns for m in merged], np.int64),
        'merged_counts': np.array([len(m.detections) for m in merged], np.int64),
        'merged_detections': (np.concatenate([m.detections for m in merged]).astype(np.int64) if merged
                              else np.zeros(0, np.int64)),
        'merged_origin': np.array([mapper.origins.get(k, (0, 0)) for k in ids], np.uint64).reshape(-1, 2),
        'carried_keys': np.array(carried, np.int64).reshape(-1, 2),
        'carried_views': np.array([mapper.carried[k] for k in carried], np.int64),
    }


def _parse_culled(data: dict, keyframes: dict) -> tuple[dict, dict, dict]:
    """({culled id: Merged}, {(keyframe, detection): views}, {culled id: origin}) of a map
    file; ValueError where they do not fit its keyframes. None in maps of older versions."""
    if 'merged_ids' not in data:
        return {}, {}, {}
    ids, into, counts = data['merged_ids'], data['merged_into'], data['merged_counts']
    n = len(ids)
    if not (ids.ndim == 1 and into.shape == (n,) and counts.shape == (n,) and data['merged_poses'].shape == (n, 4)
            and data['merged_stamps'].shape == (n,) and data['merged_origin'].shape == (n, 2)
            and all(data[k].dtype.kind in 'iu' for k in ('merged_ids', 'merged_into', 'merged_counts',
                                                          'merged_detections', 'merged_stamps', 'carried_keys',
                                                          'carried_views'))
            and np.all(counts >= 0) and int(counts.sum()) == len(data['merged_detections'])
            and np.all(np.isfinite(data['merged_poses']))):
        raise ValueError('culled keyframe arrays')
    if len(np.unique(ids)) != n or any(int(k) in keyframes for k in ids) or any(int(k) not in keyframes for k in into):
        raise ValueError('culled keyframes must be distinct from the kept ones and carried by them')
    merged, origins = {}, {}
    offsets = np.r_[0, np.cumsum(counts)]
    for i, k in enumerate(ids):
        det = data['merged_detections'][offsets[i]:offsets[i + 1]]
        if len(det) and (det.min() < -1 or det.max() >= len(keyframes[int(into[i])])):
            raise ValueError(f'culled keyframe {int(k)}: detection index out of range')
        yaw, *t = data['merged_poses'][i]
        merged[int(k)] = Merged(int(into[i]), Pose4(float(yaw), t), int(data['merged_stamps'][i]), det.astype(int))
        if data['merged_origin'][i][0]:
            origins[int(k)] = tuple(int(v) for v in data['merged_origin'][i])
    keys, views = data['carried_keys'], data['carried_views']
    if keys.ndim != 2 or keys.shape[1:] != (2,) or views.shape != (len(keys),) or np.any(views <= 0):
        raise ValueError('carried view arrays')
    carried = {}
    for (k, d), v in zip(keys, views):
        if int(k) not in keyframes or not 0 <= d < len(keyframes[int(k)]):
            raise ValueError(f'carried views of an unknown detection ({int(k)}, {int(d)})')
        carried[int(k), int(d)] = int(v)
    return merged, carried, origins


def _unit(vectors: np.ndarray) -> bool:
    """Whether every row is a unit vector, near enough (gravity, as the messages carry it)."""
    with np.errstate(over='ignore', invalid='ignore'):
        return bool(np.all(np.abs(np.linalg.norm(np.asarray(vectors, float), axis=1) - 1.0) < 0.5))


def _check_rows(rows: np.ndarray, where) -> None:
    """MapFileError for frame log rows that loading would refuse."""
    if not (np.all(np.isfinite(rows['poses'])) and np.all(np.isfinite(rows['gravity']))
            and _unit(rows['gravity'])):
        raise MapFileError(f'not saved to {where}, the frame log is not valid (a non-finite pose or gravity)')


def _write_frames(log: FrameLog, path: Path) -> str:
    """Bring the frame file beside ``path`` up to ``log``; its name. Appends the rows logged
    since this log last wrote there when that file is as it left it; else writes a new file
    (a new name: the map file on disk keeps naming the old one until it is replaced)."""
    state = log.written.get(str(path))
    if state is not None:
        name, written = state
        try:
            intact = written <= len(log) and path.with_name(name).stat().st_size == _FRAMES_HEAD + written * ROW.itemsize
        except OSError:
            intact = False
        if intact:
            rows = log.rows(written)
            _check_rows(rows, path)
            with open(path.with_name(name), 'ab') as f:
                f.write(rows.tobytes())
                f.flush()
                os.fsync(f.fileno())
            log.written[str(path)] = (name, len(log))
            return name
    rows = log.rows()
    _check_rows(rows, path)
    token = secrets.token_hex(8)
    name = f'{path.name}.{token}.frames'
    tmp = path.with_name(name + '.tmp')
    try:
        with open(tmp, 'wb') as f:
            f.write(_FRAMES_MAGIC + bytes.fromhex(token) + rows.tobytes())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path.with_name(name))
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    log.written[str(path)] = (name, len(log))
    return name


def _read_frames(path: Path, name, count: int, load: bool) -> dict:
    """The frame log rows a map file at ``path`` keeps beside it (``name``: its frame file,
    ``count`` rows), as the map's frame arrays (``load``), or {} once the file is checked to
    hold them."""
    if not isinstance(name, str) or not (match := _FRAMES_NAME.fullmatch(name)):
        raise MapFileError(f'{path}: inconsistent map file (frame file name {name!r})')
    side = path.with_name(name)
    try:
        with open(side, 'rb') as f:
            head = f.read(_FRAMES_HEAD)
            size = os.fstat(f.fileno()).st_size
            if head != _FRAMES_MAGIC + bytes.fromhex(match.group(1)):
                raise MapFileError(f'{side} is not the frame file of {path}')
            if size < _FRAMES_HEAD + count * ROW.itemsize:
                raise MapFileError(f'{side} holds fewer frames than {path} says ({count})')
            rows = np.fromfile(f, ROW, count=count) if load else None
    except OSError as exc:
        raise MapFileError(f'{path}: its frame log {side.name} cannot be read ({exc.strerror or exc}); '
                           'a map saved by a node keeps it beside the map file: copy both') from None
    return {} if rows is None else {f'frame_{k}': np.ascontiguousarray(rows[k]) for k in ROW.names}


def _remove_stale_frames(path: Path, keep: str | None) -> None:
    """Frame files beside ``path`` that its map file no longer names."""
    for side in path.parent.glob(glob_escape(path.name) + '.*.frames'):
        if side.name != keep and _FRAMES_NAME.fullmatch(side.name):
            side.unlink(missing_ok=True)


def save_map(mapper: Mapper, path, frames_beside: bool = False) -> Path:
    """Write the mapper's map to ``path`` atomically, read back and validated before it
    replaces the file there: MapFileError (the file there kept) for a map that loading would
    refuse (a non-finite value in memory must not become the autosave the next start cannot
    load). With ``frames_beside`` the frame log goes to a file beside it, by appending (see
    the module's notes): what a node's autosave does. Returns the path."""
    path = Path(path).expanduser()
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays, lists = _keyframe_arrays(mapper)
    arrays.update(_edge_arrays(mapper))
    arrays.update(_culled_arrays(mapper))
    poses = mapper.poses
    pose_ids = sorted(poses)
    arrays['pose_ids'] = np.array(pose_ids, np.int64)
    arrays['pose_values'] = np.array([[poses[k].yaw, *poses[k].t] for k in pose_ids], float).reshape(-1, 4)
    header = {'format': FORMAT, 'version': VERSION, 'keyframes': len(mapper.keyframes),
              'edges': len(arrays['edge_ids']), 'registered': len(pose_ids), 'posed': mapper.config.posed,
              'frames': len(mapper.frames), 'revision': mapper.revision, 'config': mapper.config.to_dict(), **lists}
    if frames_beside:
        header['frames_file'] = _write_frames(mapper.frames, path)
    else:
        arrays.update({f'frame_{k}': v for k, v in mapper.frames.arrays().items()})
    buffer = io.BytesIO()
    np.savez_compressed(buffer, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
    fd, tmp = tempfile.mkstemp(prefix=path.name + '.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(fd, 'wb') as f:
            f.write(buffer.getvalue())
            f.flush()
            os.fsync(f.fileno())
        try:
            read_map(tmp, frames=not frames_beside)      # the appended rows were checked as written
        except MapFileError as exc:
            raise MapFileError(f'not saved to {path}, the map is not valid: {exc}') from None
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _remove_stale_frames(path, header.get('frames_file'))
    return path


#: arrays that hold ids, counts or indices
_INTEGER_ARRAYS = ('kf_ids', 'kf_counts', 'kf_stamps', 'edge_ids', 'edge_inlier_counts', 'edge_inliers',
                   'edge_corner_counts', 'pose_ids')


def _load_arrays(path: Path) -> dict:
    """The archive's arrays; MapFileError for anything unreadable, and before reading for
    an array that declares more data than its archive member holds, or members that inflate
    past :data:`MAX_INFLATION` (a small crafted file must not make the loader allocate
    gigabytes)."""
    try:
        with zipfile.ZipFile(path) as archive:
            inflated = sum(info.file_size for info in archive.infolist())
            allowed = MAX_INFLATION * path.stat().st_size + INFLATION_ALLOWANCE
            if inflated > allowed:
                raise MapFileError(f'{path}: its arrays would inflate to {inflated / 2 ** 20:.0f} MB, more than '
                                   f'{MAX_INFLATION} times the file ({allowed / 2 ** 20:.0f} MB): a compression bomb')
            for info in archive.infolist():
                with archive.open(info) as member:
                    version = np.lib.format.read_magic(member)
                    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                            else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read(member)
                if dtype.hasobject or int(np.prod(shape, dtype=object)) * dtype.itemsize > info.file_size:
                    raise MapFileError(f'{path}: array {info.filename} declares more data than the file holds')
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, MemoryError) as exc:
        raise MapFileError(f'{path} is not a readable rfm map file ({type(exc).__name__}: {exc})') from None


def read_map(path, frames: bool = True) -> dict:
    """Read and validate a map file; returns {'header', 'keyframes', 'edges', 'poses', ...};
    MapFileError saying why for any file that is not a consistent map. Without ``frames`` a
    frame log kept beside the file is checked to be there, not read."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise MapFileError(f'no map file at {path}')
    data = _load_arrays(path)
    try:
        return _parse_map(path, data, frames)
    except (ValueError, TypeError, IndexError, KeyError, OverflowError, AttributeError) as exc:
        raise MapFileError(f'{path}: inconsistent map file ({type(exc).__name__}: {exc})') from None


def _parse_map(path: Path, data: dict, load_frames: bool = True) -> dict:
    if 'header' not in data:
        raise MapFileError(f'{path} is not an rfm map file (no header)')
    try:
        header = json.loads(bytes(data['header']).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapFileError(f'{path}: corrupt header ({exc})') from None
    if header.get('format') != FORMAT:
        raise MapFileError(f'{path} is not an rfm map file (format {header.get("format")!r})')
    if header.get('version') != VERSION:
        raise MapFileError(f'{path} has map format version {header.get("version")}; this rfm reads '
                           f'version {VERSION}')
    need = ['kf_ids', 'kf_counts', 'kf_stamps', 'kf_gravity', 'kf_intrinsics', 'det_boxes', 'det_scores',
            'det_embeddings', 'det_boxes_2d', 'edge_ids', 'edge_poses', 'edge_scores', 'edge_active', 'edge_inlier_counts',
            'edge_inliers', 'edge_inlier_scores', 'edge_corner_counts', 'edge_corners', 'pose_ids', 'pose_values']
    missing = [k for k in need if k not in data]
    if missing:
        raise MapFileError(f'{path}: missing arrays {missing}')
    wrong = [k for k in _INTEGER_ARRAYS if data[k].dtype.kind not in 'iu']
    if wrong:
        raise MapFileError(f'{path}: arrays {wrong} must hold integers')
    for key in _HEADER_COUNTS:
        value = header.get(key, 0)
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < MAX_ID:
            raise MapFileError(f'{path}: header field {key!r} must be an integer in [0, 2^62), got {value!r}')
    for key in _HEADER_STRINGS:
        value = header.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise MapFileError(f'{path}: header field {key!r} must be a list of strings')
    frame_keys = [f'frame_{k}' for k in ROW.names]
    if 'frames_file' in header:
        if any(k in data for k in frame_keys):
            raise MapFileError(f'{path}: inconsistent map file (frames both inside and beside it)')
        data.update(_read_frames(path, header['frames_file'], header.get('frames', 0), load_frames))
    floats = [k for k, v in data.items() if k != 'header' and v.dtype.kind in 'fc'
              and not np.all(np.isfinite(v) | (k in _UNMEASURED) & np.isnan(v))]
    if floats:
        raise MapFileError(f'{path}: arrays {sorted(floats)} hold non-finite values (NaN or infinity)')
    n_kf, n_det, n_edge = len(data['kf_ids']), int(data['kf_counts'].sum()), len(data['edge_ids'])
    checks = [
        (len(data['kf_counts']) == n_kf and len(data['kf_stamps']) == n_kf, 'keyframe arrays differ in length'),
        (data['kf_gravity'].shape == (n_kf, 3) and data['kf_intrinsics'].shape == (n_kf, 6), 'keyframe shapes'),
        (np.all(data['kf_counts'] >= 0), 'negative detection counts'),
        (data['det_boxes'].shape == (n_det, 7) and len(data['det_scores']) == n_det, 'detection arrays'),
        (len(data['det_embeddings']) == n_det and data['det_boxes_2d'].shape == (n_det, 4), 'detection arrays'),
        (len(header.get('det_labels', [])) == n_det, 'detection labels'),
        (len(header.get('kf_frame_ids', [])) == n_kf, 'keyframe frame ids'),
        (data['kf_ids'].ndim == 1 and data['edge_ids'].shape == (n_edge, 2), 'id arrays'),
        (data['edge_poses'].shape == (n_edge, 4) and len(data['edge_scores']) == n_edge
         and len(data['edge_active']) == n_edge and len(data['edge_inlier_counts']) == n_edge
         and len(data['edge_corner_counts']) == n_edge, 'edge arrays'),
        (data['edge_inliers'].ndim == 2 and data['edge_inliers'].shape[1] == 2
         and data['edge_corners'].ndim == 2 and data['edge_corners'].shape[1] == 5, 'edge match arrays'),
        (np.all(data['edge_inlier_counts'] >= 0) and np.all(data['edge_corner_counts'] >= 0), 'negative counts'),
        (int(data['edge_inlier_counts'].sum()) == len(data['edge_inliers']), 'edge inlier counts'),
        (len(data['edge_inlier_scores']) == len(data['edge_inliers']), 'edge inlier scores'),
        (int(data['edge_corner_counts'].sum()) == len(data['edge_corners']), 'edge corner counts'),
        (data['pose_values'].shape == (len(data['pose_ids']), 4), 'pose arrays'),
        (len(np.unique(data['kf_ids'])) == n_kf, 'duplicate keyframe ids'),
        (np.all((data['kf_ids'] >= 0) & (data['kf_ids'] < MAX_ID)) and np.all(data['kf_stamps'] >= 0),
         'keyframe ids or stamps out of range'),
        (np.all(np.isin(data['edge_ids'], data['kf_ids'])), 'edges reference unknown keyframes'),
        (np.all(np.isin(data['pose_ids'], data['kf_ids'])), 'poses reference unknown keyframes'),
    ]
    if any(k in data for k in frame_keys):
        n_frames = len(data.get('frame_stamps', ()))
        checks += [
            (all(k in data and len(data[k]) == n_frames for k in frame_keys), 'frame arrays differ in length'),
            (data['frame_poses'].shape == (n_frames, 4) and data['frame_gravity'].shape == (n_frames, 3),
             'frame shapes'),
            (_unit(data['frame_gravity']), 'frame gravity is not a unit vector'),
        ]
    if 'kf_origin' in data:                                   # none in maps of older rfm versions
        checks += [(data['kf_origin'].shape == (n_kf, 2) and data['kf_origin'].dtype.kind in 'iu',
                    'keyframe origins')]
    if 'kf_full' in data or 'det_full_boxes' in data:       # none in maps of older rfm versions
        full = data.get('det_full_boxes', np.zeros(0))
        checks += [(data.get('kf_full', np.zeros(0)).shape == (n_kf,) and full.shape == (n_det, 7), 'full box arrays')]
    if 'kf_camera_height' in data:                            # none in maps of older rfm versions
        checks += [(data['kf_camera_height'].shape == (n_kf,) and data['kf_camera_height'].dtype.kind == 'f',
                    'keyframe camera heights')]
    if 'kf_wall_counts' in data:                              # none in maps of older rfm versions
        wc, walls = data['kf_wall_counts'], data.get('kf_walls', np.zeros(0))
        checks += [(wc.shape == (n_kf,) and wc.dtype.kind in 'iu' and np.all(wc >= 0) and walls.ndim == 2
                    and walls.shape == (int(wc.sum()), 3) and walls.dtype.kind == 'f', 'keyframe wall arrays')]
    if 'kf_cloud_counts' in data:                             # none in maps of older rfm versions
        cc, clouds = data['kf_cloud_counts'], data.get('kf_clouds', np.zeros(0))
        checks += [(cc.shape == (n_kf,) and cc.dtype.kind in 'iu' and np.all(cc >= 0) and clouds.ndim == 2
                    and clouds.shape == (int(cc.sum()), 3) and clouds.dtype.kind == 'f', 'keyframe cloud arrays')]
    for ok, what in checks:
        if not ok:
            raise MapFileError(f'{path}: inconsistent map file ({what})')
    try:
        config = MapperConfig.from_dict(header['config']) if 'config' in header else None
    except (TypeError, ValueError) as exc:
        raise MapFileError(f'{path}: bad mapper configuration ({exc})') from None
    frames = {k[len('frame_'):]: data[k] for k in frame_keys if k in data}
    keyframes = {}
    offsets = np.r_[0, np.cumsum(data['kf_counts'])]
    wall_offsets = np.r_[0, np.cumsum(data['kf_wall_counts'])] if 'kf_wall_counts' in data else None
    cloud_offsets = np.r_[0, np.cumsum(data['kf_cloud_counts'])] if 'kf_cloud_counts' in data else None
    labels = header['det_labels']
    for i, k in enumerate(data['kf_ids']):
        a, b = offsets[i], offsets[i + 1]
        w, h, fx, fy, cx, cy = data['kf_intrinsics'][i]
        intr = CameraIntrinsics(fx, fy, cx, cy, int(w), int(h)) if w > 0 else None
        try:
            keyframes[int(k)] = FrameObservations(
                stamp_ns=int(data['kf_stamps'][i]), frame_id=header['kf_frame_ids'][i], intrinsics=intr,
                gravity_cam=data['kf_gravity'][i], boxes=data['det_boxes'][a:b], scores=data['det_scores'][a:b],
                labels=list(labels[a:b]), embeddings=data['det_embeddings'][a:b],
                boxes_2d=data['det_boxes_2d'][a:b], backend=header.get('kf_backends', [''] * n_kf)[i],
                full_boxes=data['det_full_boxes'][a:b] if 'kf_full' in data and data['kf_full'][i] else None,
                camera_height=float(data['kf_camera_height'][i]) if 'kf_camera_height' in data else float('nan'),
                walls=(data['kf_walls'][wall_offsets[i]:wall_offsets[i + 1]] if wall_offsets is not None
                       else np.zeros((0, 3))),
                cloud=(data['kf_clouds'][cloud_offsets[i]:cloud_offsets[i + 1]] if cloud_offsets is not None
                       else np.zeros((0, 3), np.float32)))
        except ValueError as exc:
            raise MapFileError(f'{path}: keyframe {int(k)}: {exc}') from None
    edges = []
    io_, ic = np.r_[0, np.cumsum(data['edge_inlier_counts'])], np.r_[0, np.cumsum(data['edge_corner_counts'])]
    for i, (s, t) in enumerate(data['edge_ids']):
        inl = data['edge_inliers'][io_[i]:io_[i + 1]]
        if len(inl) and (inl[:, 0].max() >= len(keyframes[int(s)]) or inl[:, 1].max() >= len(keyframes[int(t)])
                         or inl.min() < 0):
            raise MapFileError(f'{path}: edge {int(s)}->{int(t)} references missing detections')
        yaw, *tr = data['edge_poses'][i]
        edges.append(EdgeRecord(int(s), int(t), Pose4(float(yaw), tr), inl,
                                data['edge_inlier_scores'][io_[i]:io_[i + 1]],
                                data['edge_corners'][ic[i]:ic[i + 1]], float(data['edge_scores'][i])))
    poses = {int(k): Pose4(float(v[0]), v[1:]) for k, v in zip(data['pose_ids'], data['pose_values'])}
    origins = {int(k): (int(s), int(i)) for k, (s, i) in zip(data['kf_ids'], data.get('kf_origin', ())) if s}
    try:
        merged, carried, culled_origins = _parse_culled(data, keyframes)
    except (ValueError, TypeError, KeyError) as exc:
        raise MapFileError(f'{path}: inconsistent map file ({exc})') from None
    origins.update(culled_origins)
    return {'header': header, 'keyframes': keyframes, 'edges': edges, 'poses': poses,
            'edge_active': [bool(a) for a in data['edge_active']],
            'config': config, 'frames': frames, 'origins': origins, 'merged': merged, 'carried': carried}


def load_map(mapper: Mapper, path, use_config: bool = True) -> dict:
    """Replace the mapper's map with the one in ``path`` (validated first: on error the
    mapper is untouched). The saved poses and edge decisions are restored as they were;
    new keyframes continue from them, in its frame (:attr:`IncrementalAverager.reference`: a
    second session's keyframes join it, never the other way round). With ``use_config`` the mapper takes the file's
    configuration (the one that built the map), when the file has one. Returns the file
    header."""
    content = read_map(path)
    config = content['config'] if use_config and content['config'] is not None else mapper.config
    fresh = Mapper(config, matcher=mapper.matcher)          # built aside, swapped in on success
    try:
        for k in sorted(content['keyframes']):
            fresh.add_keyframe(k, content['keyframes'][k])
        for e in content['edges']:
            fresh.add_edge(e)
        fresh.restore(content['poses'], [e for e, a in zip(content['edges'], content['edge_active']) if a])
        fresh.merged, fresh.carried = content['merged'], content['carried']
        if content['frames']:
            fresh.restore_frames(content['frames'])
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        raise MapFileError(f'{path}: inconsistent map file ({type(exc).__name__}: {exc})') from None
    fresh.origins = content['origins']
    fresh.averager.reference = set(content['poses'])      # the loaded map stays the map (a second session joins it)
    fresh.averager.sizes = fresh.culled_sizes()
    fresh._cull_due = set()                                # its keyframes are as they were saved
    fresh.revision = content['header'].get('revision', 0) + 1
    fresh.mode = mapper.mode
    mapper.__dict__.update(fresh.__dict__)
    return content['header']
