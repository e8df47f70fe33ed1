"""Crafted map files are refused with a reason and never cost the current map (#19 rows 2b, 4)."""
import io
import json
import zipfile

import numpy as np
import pytest

from rfm_core.evaluation.pipeline import run_capture
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
