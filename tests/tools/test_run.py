"""`rfm run --bag`: the whole graph on a generated bag, in one process and as processes."""
import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip('rclpy')

from rfm_core.evaluation.report import evaluate_run, read_ground_truth  # noqa: E402
from rfm_core.mapping.map_io import load_map  # noqa: E402
from rfm_core.mapping.mapper import Mapper  # noqa: E402
from rfm_core.sim.capture import CaptureConfig  # noqa: E402
from rfm_core.sim.capture import Capture  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def short_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('bags') / 'short'
    Capture(CaptureConfig(seed=40, frames=40, fps=8)).write_bag(path)
    return path


@pytest.mark.parametrize('processes', [False, True], ids=['one-process', 'processes'])
def test_rfm_run_on_a_bag_writes_every_output_and_maps_the_room(short_bag, tmp_path, processes):
    out = tmp_path / 'out'
    cmd = [shutil.which('rfm'), 'run', '--bag', str(short_bag), '--output', str(out), '--backend', 'ground_truth',
           '--quiet', '--settle', '2']
    if processes:
        cmd.append('--processes')
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for name in ('map.rfm', 'trajectory.tum', 'objects.json', 'report.md', 'top_down.png',
                 'outputs.mcap/metadata.yaml'):
        assert (out / name).is_file(), name
    assert 'vs ground truth' in proc.stdout
    mapper = Mapper()
    load_map(mapper, out / 'map.rfm')
    acc = evaluate_run(mapper, read_ground_truth(short_bag))
    loc, m = acc['localization'], acc['mapping']
    assert len(mapper.keyframes) >= 5
    assert loc['registered'] >= 0.9 and loc['ATE_median'] < 0.06 and loc['ARE_median'] < 3.0, loc
    assert m['AP25'] > 0.5, m
    # a pose for every localized frame, the keyframes beside them
    tum = np.loadtxt(out / 'trajectory.tum')
    assert tum.shape == (len(mapper.frame_poses()), 8) and len(tum) >= 0.9 * 40
    assert np.all(np.diff(tum[:, 0]) > 0)
    assert np.loadtxt(out / 'keyframes.tum').shape == (len(mapper.poses), 8)
    # the recording has the mapper's outputs
    from rosbags.highlevel import AnyReader
    with AnyReader([out / 'outputs.mcap']) as reader:
        topics = {c.topic for c in reader.connections}
    assert {'/rfm/detections', '/rfm/keyframes', '/rfm/object_map', '/rfm/keyframe_poses'} <= topics


def test_rfm_run_gives_an_rgb_only_detector_along_ray_errors(tmp_path):
    """`rfm run` passes the matcher and mapper the monocular range error exactly when the
    detector judges distance from RGB alone; --param still overrides it."""
    from rfm_bringup.cli import build_parser
    from rfm_bringup.run import _params
    from rfm_core.matching.config import MONOCULAR_RANGE_ERROR

    def params(*extra):
        return _params(build_parser().parse_args(['run', '--bag', 'x', '--backend', 'ground_truth', *extra]),
                       tmp_path)
    rgb = params('--preset', 'rgb')
    for node in ('matcher', 'mapper'):
        assert (rgb[node]['range_error'], rgb[node]['range_error_per_m']) == MONOCULAR_RANGE_ERROR
    assert 'range_error' not in params('--preset', 'rgbd')['matcher']
    assert params('--preset', 'rgb', '--param', 'matcher.range_error:=0.05')['matcher']['range_error'] == 0.05
    with pytest.raises(SystemExit):
        params('--preset', 'sonar')
