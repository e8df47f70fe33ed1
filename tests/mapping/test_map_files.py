"""Crafted map files are refused with a reason and never cost the current map (#19 rows 2b, 4)."""
import io
import json
import zipfile

import numpy as np
import pytest

from rfm_core.evaluation.pipeline import run_capture
from rfm_core.geometry import Pose4
from rfm_core.mapping.map_io import MapFileError, load_map, save_map
from rfm_core.mapping.mapper import Mapper
from rfm_core.sim.capture import CaptureConfig


@pytest.fixture(scope='module')
def saved(tmp_path_factory):
    mapped = run_capture(CaptureConfig(seed=41, frames=30, fps=5), 'ground_truth:rgbd', noise_seed=1)
    return save_map(mapped.mapper, tmp_path_factory.mktemp('map') / 'room.rfm')


def _arrays(path):
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _write(path, arrays):
    np.savez(path, **arrays)
    return path


def _with_header(arrays, **changes):
    header = json.loads(bytes(arrays['header']).decode())
    header.update(changes)
    return dict(arrays, header=np.frombuffer(json.dumps(header).encode(), np.uint8))


def _culled(good, culled=999_999, into=None, detection=0):
    """Arrays of one keyframe culled into another (keyframe culling), with one part crafted."""
    into = int(good['kf_ids'][-1]) if into is None else into
    return dict(merged_ids=np.array([culled]), merged_into=np.array([into]), merged_poses=np.zeros((1, 4)),
                merged_stamps=np.array([1]), merged_counts=np.array([1]), merged_detections=np.array([detection]),
                merged_origin=np.zeros((1, 2), np.uint64), carried_keys=np.zeros((0, 2), np.int64),
                carried_views=np.zeros(0, np.int64))


def test_crafted_map_files_are_refused_and_the_map_is_kept(saved, tmp_path):
    mapper = Mapper()
    load_map(mapper, saved)
    keyframes, poses, revision = dict(mapper.keyframes), dict(mapper.poses), mapper.revision
    good = _arrays(saved)
    n_tracks = len(mapper.tracks())
    crafted = {
        'float counts': dict(good, kf_counts=good['kf_counts'].astype(float)),
        'short edge arrays': dict(good, edge_inlier_counts=good['edge_inlier_counts'][:-1]),
        'edge ids of the wrong shape': dict(good, edge_ids=good['edge_ids'][:, :1]),
        'a revision that is not a number': _with_header(good, revision='seven'),
        'a keyframe count that is not a number': _with_header(good, keyframes=[1]),
        'inliers beyond the detections': dict(good, edge_inliers=good['edge_inliers'] + 10_000),
        'a culled keyframe carried by an unknown one': dict(good, **_culled(good, into=10_000)),
        'a culled keyframe that is also kept': dict(good, **_culled(good, culled=int(good['kf_ids'][0]))),
        'a culled detection beyond the carrier\'s': dict(good, **_culled(good, detection=10_000)),
        'carried views of an unknown detection': dict(good, carried_keys=np.array([[10_000, 0]]),
                                                      carried_views=np.array([2])),
    }
    for what, arrays in crafted.items():
        with pytest.raises(MapFileError):
            load_map(mapper, _write(tmp_path / 'bad.npz', arrays))
        assert mapper.keyframes.keys() == keyframes.keys(), what
        assert mapper.poses.keys() == poses.keys() and mapper.revision == revision, what
    assert len(mapper.tracks()) == n_tracks
    # the same arrays, not crafted, load: a map with a culled keyframe
    load_map(mapper, _write(tmp_path / 'culled.npz', dict(good, **_culled(good))))
    assert mapper.merged.keys() == {999_999} and mapper.knows(999_999) and len(mapper.tracks()) == n_tracks


def test_an_array_declaring_more_data_than_the_file_holds_is_refused_before_reading(saved, tmp_path):
    """A 1e12 x 7 float64 array (56 TB) declared in a file of a few kB."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {'descr': '<f8', 'fortran_order': False,
                                                  'shape': (10 ** 12, 7)})
    bad = tmp_path / 'bomb.npz'
    with zipfile.ZipFile(saved) as src, zipfile.ZipFile(bad, 'w') as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == 'det_boxes.npy':
                data = np.lib.format.magic(1, 0) + buffer.getvalue()[8:] + b'\0' * 64
            dst.writestr(info.filename, data)
    assert bad.stat().st_size < 10 * saved.stat().st_size
    mapper = Mapper()
    with pytest.raises(MapFileError, match='declares more data'):
        load_map(mapper, bad)
    assert not mapper.keyframes


def test_map_files_are_checked_as_strictly_as_messages(saved, tmp_path):
    """Every float finite, every stored setting within its declared range, every header field
    typed and within what messages carry."""
    mapper = Mapper()
    load_map(mapper, saved)
    keyframes = dict(mapper.keyframes)
    good = _arrays(saved)
    header = json.loads(bytes(good['header']).decode())
    config = header['config']

    def with_setting(section, name, value):
        changed = json.loads(json.dumps(config))
        changed[section][name] = value
        return _with_header(good, config=changed)

    nan_at_first = lambda a: np.where(np.arange(a.size).reshape(a.shape) == 0, np.nan, a).astype(a.dtype)  # noqa: E731
    crafted = {
        'NaN detection scores': (dict(good, det_scores=nan_at_first(good['det_scores'])), 'non-finite'),
        'NaN 2D boxes': (dict(good, det_boxes_2d=nan_at_first(good['det_boxes_2d'])), 'non-finite'),
        'an infinite edge score': (dict(good, edge_scores=good['edge_scores'] + np.inf), 'non-finite'),
        'NaN corner matches': (dict(good, edge_corners=np.full((len(good['edge_corners']), 5), np.nan)),
                               'non-finite') if len(good['edge_corners']) else None,
        'a stored setting out of its range': (with_setting('averaging', 'translation_scale_m', 0.0),
                                              'translation_scale_m'),
        'keyframe ids past 2^62': (dict(good, kf_ids=good['kf_ids'] + 2 ** 62,
                                        edge_ids=good['edge_ids'] + 2 ** 62, pose_ids=good['pose_ids'] + 2 ** 62),
                                   'out of range'),
        'a negative revision': (_with_header(good, revision=-1), 'revision'),
        'a revision past 2^64': (_with_header(good, revision=2 ** 64), 'revision'),
        'labels that are not strings': (_with_header(good, det_labels=[7] * len(header['det_labels'])), 'det_labels'),
        'frame ids that are not strings': (_with_header(good, kf_frame_ids=[None] * len(header['kf_frame_ids'])),
                                           'kf_frame_ids'),
    }
    for what, case in crafted.items():
        if case is None:
            continue
        arrays, reason = case
        with pytest.raises(MapFileError, match=reason):
            load_map(mapper, _write(tmp_path / 'bad.npz', arrays))
        assert mapper.keyframes.keys() == keyframes.keys(), what
    # a camera height not measured is NaN, and loads
    load_map(mapper, _write(tmp_path / 'heights.npz', dict(good, kf_camera_height=np.full(len(good['kf_ids']),
                                                                                             np.nan))))
    assert mapper.keyframes.keys() == keyframes.keys()


def test_a_compression_bomb_is_refused_before_it_inflates(saved, tmp_path):
    """An array of 300 MB of zeros deflates to a few hundred kB; the file is refused from its
    directory before anything is inflated."""
    import resource
    rows = 300 * 2 ** 20 // 56
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {'descr': '<f8', 'fortran_order': False, 'shape': (rows, 7)})
    bad = tmp_path / 'bomb.npz'
    with zipfile.ZipFile(saved) as src, zipfile.ZipFile(bad, 'w', zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename != 'det_boxes.npy':
                dst.writestr(info.filename, src.read(info))
                continue
            with dst.open('det_boxes.npy', 'w', force_zip64=True) as member:
                member.write(np.lib.format.magic(1, 0) + header.getvalue()[8:])
                zeros = bytes(2 ** 20)
                for _ in range(rows * 56 // len(zeros)):
                    member.write(zeros)
                member.write(bytes(rows * 56 % len(zeros)))
    assert bad.stat().st_size < 3 * 2 ** 20
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    mapper = Mapper()
    with pytest.raises(MapFileError, match='compression bomb'):
        load_map(mapper, bad)
    assert not mapper.keyframes
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100 * 1024     # kB: nothing inflated


def test_saving_never_replaces_a_good_file_with_one_loading_would_refuse(saved, tmp_path):
    mapper = Mapper()
    load_map(mapper, saved)
    target = tmp_path / 'map.rfm'
    save_map(mapper, target)
    good_bytes = target.read_bytes()
    first = min(mapper.keyframes)
    mapper.keyframes[first].scores[:] = np.nan                   # a NaN in memory
    with pytest.raises(MapFileError, match='not saved'):
        save_map(mapper, target)
    assert target.read_bytes() == good_bytes and not list(tmp_path.glob('*.tmp'))


def _mutated(good: dict, rng) -> tuple:
    """A real map file's arrays with one thing changed: an array's dtype, shape or values, or
    a header field. Returns (arrays, what)."""
    arrays = dict(good)
    names = sorted(k for k in good if k != 'header')
    if rng.random() < 0.25:
        header = json.loads(bytes(good['header']).decode())
        key = rng.choice(sorted(header))
        value = rng.choice([None, -1, 2 ** 64, 1e308, float('nan'), 'x', [], {}, [7] * 3, True,
                            header[key] if not isinstance(header[key], dict) else {'averaging': {'window': -5}}])
        return _with_header(arrays, **{key: value}), f'header {key}={value!r:.40}'
    name = rng.choice(names)
    a = good[name]
    kind = rng.randrange(4)
    if kind == 0:                                            # another dtype
        dtype = rng.choice([np.float32, np.float64, np.int64, np.uint8, np.bool_])
        arrays[name] = a.astype(dtype)
    elif kind == 1 and a.ndim:                               # a row more or fewer
        arrays[name] = a[:-1] if len(a) and rng.random() < 0.5 else np.concatenate([a, a[:1]])
    elif kind == 2 and a.size:                               # hostile values
        b = a.copy().reshape(-1)
        i = rng.randrange(b.size)
        if b.dtype.kind == 'f':
            bad = [np.nan, np.inf, -1e300 if b.dtype.itemsize == 8 else -1e30, 1e30]
        elif b.dtype.kind in 'iu':
            info = np.iinfo(b.dtype)
            bad = [info.min, info.max, *([-1] if info.min < 0 else []), *([2 ** 62] if info.max >= 2 ** 62 else [])]
        else:
            bad = [not b[i]]
        b[i] = rng.choice(bad)
        arrays[name] = b.reshape(a.shape)
    else:                                                    # another shape
        arrays[name] = a.reshape(-1) if a.ndim > 1 else a.reshape(-1, 1)
    return arrays, f'{name} ({"dtype shape values reshape".split()[kind]})'


def test_mutated_map_files_are_refused_or_load_into_a_working_map(saved, tmp_path):
    """Each array's dtype, shape and values and each header field of a real map file,
    mutated (``RFM_FUZZ_N`` / 2 files; ``make fuzz``: thousands): loading either refuses the
    file with MapFileError, the current map kept, or gives a map whose poses are finite and
    which solves and builds its tracks. Never another error."""
    import os
    import random
    rng = random.Random(int(os.environ.get('RFM_FUZZ_SEED', '19')))
    good = _arrays(saved)
    mapper = Mapper()
    load_map(mapper, saved)
    kept = set(mapper.keyframes)
    refused = 0
    for i in range(int(os.environ.get('RFM_FUZZ_N', '400')) // 2):
        arrays, what = _mutated(good, rng)
        path = _write(tmp_path / 'mutated.npz', arrays)
        try:
            load_map(mapper, path)
        except MapFileError:
            refused += 1
            assert set(mapper.keyframes) == kept, (i, what)
            continue
        try:
            mapper.update(force_full=True)
            mapper.tracks()
        except Exception as exc:  # noqa: BLE001 - the point of the test
            pytest.fail(f'file {i} ({what}) loaded into a map that fails: {exc!r}')
        assert all(np.isfinite(p.yaw) and np.all(np.isfinite(p.t)) for p in mapper.poses.values()), (i, what)
        load_map(mapper, saved)                               # back to the good map
    assert refused > 0


def test_an_autosave_appends_the_frames_logged_since_the_last_one(tmp_path):
    """A node's map file keeps its frame log beside it and each autosave appends the new
    frames: what an autosave writes does not grow with how long the run has been (#54 row 7)."""
    from rfm_core.mapping.frame_log import ROW
    from rfm_core.observations import FrameTrack

    mapped = run_capture(CaptureConfig(seed=41, frames=30, fps=5), 'ground_truth:rgbd', noise_seed=1).mapper
    path = tmp_path / 'room.rfm'
    track = next(iter(mapped.frames.rows()))

    def log(count):                       # frames of a camera that stays by the first logged one
        for i in range(count):
            mapped.add_frame(FrameTrack(int(mapped.frames.rows()[-1]['stamps']) + 1, 'camera', track['gravity'],
                                        int(track['keyframes']), int(track['keyframe_stamps']),
                                        Pose4(float(track['poses'][0]), track['poses'][1:]), num_inliers=3))

    save_map(mapped, path, frames_beside=True)
    (side,) = tmp_path.glob('room.rfm.*.frames')
    sizes = [(path.stat().st_size, side.stat().st_size)]
    for _ in range(2):
        log(5000)
        save_map(mapped, path, frames_beside=True)
        sizes.append((path.stat().st_size, side.stat().st_size))
    assert [p.name for p in tmp_path.glob('room.rfm.*.frames')] == [side.name]        # one file, appended to
    assert max(abs(s[0] - sizes[0][0]) for s in sizes) < 2000, sizes                   # the map file: the same
    assert [b - a for (_, a), (_, b) in zip(sizes, sizes[1:])] == [5000 * ROW.itemsize] * 2
    loaded = Mapper()
    load_map(loaded, path)
    assert len(loaded.frames) == len(mapped.frames)
    np.testing.assert_array_equal(loaded.frames.rows(), mapped.frames.rows())
    assert loaded.frame_poses().keys() == mapped.frame_poses().keys()
    # rows appended by a save that failed later are not the map's; a self-contained copy holds them all
    with open(side, 'ab') as f:
        f.write(mapped.frames.rows()[:3].tobytes())
    load_map(loaded, path)
    assert len(loaded.frames) == len(mapped.frames)
    copy = save_map(mapped, tmp_path / 'copy.rfm')
    assert not list(tmp_path.glob('copy.rfm.*.frames')) and 'frame_stamps' in _arrays(copy)
    # a frame log that went missing or is another map's: refused with the reason, the map kept
    moved = side.rename(tmp_path / 'elsewhere')
    with pytest.raises(MapFileError, match='copy both'):
        load_map(loaded, path)
    moved.rename(side)
    head = side.read_bytes()
    side.write_bytes(head[:8] + bytes(8) + head[16:])
    with pytest.raises(MapFileError, match='not the frame file'):
        load_map(loaded, path)
    side.write_bytes(head[:16 + 10 * ROW.itemsize])
    with pytest.raises(MapFileError, match='fewer frames'):
        load_map(loaded, path)
    side.write_bytes(head)
    good = _arrays(path)
    for name in ('../' + side.name, '/etc/passwd', 7, side.name.replace('.frames', '.other'), None):
        with pytest.raises(MapFileError, match='frame file name'):
            load_map(loaded, _write(tmp_path / 'crafted.npz', _with_header(good, frames_file=name)))
    with pytest.raises(MapFileError, match='fewer frames'):
        load_map(loaded, _write(tmp_path / 'crafted.npz', _with_header(good, frames=2 ** 61)))
    with pytest.raises(MapFileError, match='both inside and beside'):
        load_map(loaded, _write(tmp_path / 'crafted.npz', dict(_arrays(copy), header=good['header'])))
    assert len(loaded.frames) == len(mapped.frames)
    # the next autosave, from a log that did not write that file: a new file, the old one removed
    load_map(loaded, path)
    save_map(loaded, path, frames_beside=True)
    (new,) = tmp_path.glob('room.rfm.*.frames')
    assert new.name != side.name
    np.testing.assert_array_equal(np.fromfile(new, ROW, offset=16), mapped.frames.rows())


def test_mutated_frame_files_are_refused_or_load_into_a_working_map(saved, tmp_path):
    """The frame file an autosave keeps beside the map, cut short or with bytes changed
    (its head, a row's values: NaN, huge, another id), ``RFM_FUZZ_N`` / 10 times: refused with
    MapFileError, the current map kept, or loaded with every frame pose finite."""
    import os
    import random

    from rfm_core.mapping.frame_log import ROW
    rng = random.Random(int(os.environ.get('RFM_FUZZ_SEED', '19')) + 1)
    mapper = Mapper()
    load_map(mapper, saved)
    path = save_map(mapper, tmp_path / 'room.rfm', frames_beside=True)
    (side,) = tmp_path.glob('room.rfm.*.frames')
    good = side.read_bytes()
    assert len(good) == 16 + len(mapper.frames) * ROW.itemsize > 16
    kept, refused = set(mapper.keyframes), 0
    for i in range(max(20, int(os.environ.get('RFM_FUZZ_N', '400')) // 10)):
        data = bytearray(good)
        kind = rng.randrange(3)
        if kind == 0:
            data = data[:rng.randrange(len(data))]
        elif kind == 1:
            for _ in range(rng.randrange(1, 8)):
                data[rng.randrange(len(data))] = rng.randrange(256)
        else:
            row = rng.randrange(len(mapper.frames))
            field = rng.choice(['poses', 'gravity', 'keyframes', 'stamps'])
            rows = np.frombuffer(bytes(data[16:]), ROW).copy()
            rows[field][row] = rng.choice([np.nan, np.inf, -1, 2 ** 62, 1e308]) if field in ('poses', 'gravity') \
                else rng.choice([-1, 2 ** 62, 0])
            data[16:] = rows.tobytes()
        side.write_bytes(bytes(data))
        try:
            load_map(mapper, path)
        except MapFileError:
            refused += 1
            assert set(mapper.keyframes) == kept, (i, kind)
            continue
        poses = mapper.frame_poses()
        assert all(np.all(np.isfinite(m)) for m in poses.values()), (i, kind)
        load_map(mapper, saved)
    assert refused > 0
