"""The graph split over two hosts (#19 item 5): the detector (and the camera, here the demo
bag played) in one Linux network namespace, matcher and mapper in another, joined by a veth
pair; DDS discovers over that link (UDP only: no shared memory, no localhost). The map the
mapper saves must match the bag's ground truth. Needs root and network namespaces: skipped,
saying why, where the kernel or the user forbid them."""
import json
import os
import random
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

pytest.importorskip('rclpy')
from ament_index_python.packages import get_package_prefix  # noqa: E402

from rfm_bringup.run import BAG_REMAPS  # noqa: E402
from rfm_core.evaluation.report import evaluate_run, read_ground_truth  # noqa: E402
from rfm_core.mapping.map_io import load_map  # noqa: E402
from rfm_core.mapping.mapper import Mapper  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[2]
UDP_ONLY = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors><transport_descriptor>
    <transport_id>udp</transport_id><type>UDPv4</type>
    <sendBufferSize>4194304</sendBufferSize><receiveBufferSize>4194304</receiveBufferSize>
  </transport_descriptor></transport_descriptors>
  <participant profile_name="udp_only" is_default_profile="true"><rtps>
    <userTransports><transport_id>udp</transport_id></userTransports>
    <useBuiltinTransports>false</useBuiltinTransports>
  </rtps></participant>
</profiles>
"""


def _sh(*cmd):
    return subprocess.run(cmd, capture_output=True, text=True)


@pytest.fixture
def two_hosts():
    """Namespaces (a, b) joined by veth, 10.77.x.1/.2, multicast routed over the link."""
    if os.geteuid() != 0 or shutil.which('ip') is None:
        pytest.skip('network namespaces need root and iproute2 (ip)')
    tag = f'{random.randrange(16 ** 4):04x}'
    a, b = f'rfm_a_{tag}', f'rfm_b_{tag}'
    subnet = f'10.77.{random.randrange(1, 250)}'
    made = _sh('ip', 'netns', 'add', a)
    if made.returncode:
        pytest.skip(f'cannot create a network namespace here: {made.stderr.strip()}')
    try:
        steps = [('ip', 'netns', 'add', b),
                 ('ip', 'link', 'add', f'va{tag}', 'type', 'veth', 'peer', 'name', f'vb{tag}'),
                 ('ip', 'link', 'set', f'va{tag}', 'netns', a), ('ip', 'link', 'set', f'vb{tag}', 'netns', b)]
        for ns, dev, ip in ((a, f'va{tag}', f'{subnet}.1'), (b, f'vb{tag}', f'{subnet}.2')):
            steps += [('ip', '-n', ns, 'addr', 'add', f'{ip}/24', 'dev', dev),
                      ('ip', '-n', ns, 'link', 'set', dev, 'up', 'multicast', 'on'),
                      ('ip', '-n', ns, 'link', 'set', 'lo', 'up'),
                      ('ip', '-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)]
        for step in steps:
            done = _sh(*step)
            if done.returncode:
                pytest.skip(f'cannot join network namespaces here ({" ".join(step)}: {done.stderr.strip()})')
        yield a, b
    finally:
        _sh('ip', 'netns', 'del', a)
        _sh('ip', 'netns', 'del', b)


def _exe(package, name):
    return os.path.join(get_package_prefix(package), 'lib', package, name)


def test_detector_on_one_host_matcher_and_mapper_on_another(two_hosts, tmp_path):
    a, b = two_hosts
    profile = tmp_path / 'udp_only.xml'
    profile.write_text(UDP_ONLY)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', FASTRTPS_DEFAULT_PROFILES_FILE=str(profile))
    env.pop('FASTDDS_DEFAULT_PROFILES_FILE', None)
    bag = ROOT / 'bags' / 'demo'
    map_path = tmp_path / 'map.rfm'
    logs = {}

    def start(ns, name, cmd):
        logs[name] = open(tmp_path / f'{name}.log', 'w')
        return subprocess.Popen(['ip', 'netns', 'exec', ns, *cmd], env=env, stdout=logs[name],
                                stderr=subprocess.STDOUT)

    remaps = [x for k, v in BAG_REMAPS.items() if k != 'ground_truth/detections' for x in ('-r', f'{k}:={v}')]
    procs = {
        'matcher': start(b, 'matcher', [_exe('rfm_matcher_node', 'matcher'), '--ros-args', '-p', 'use_sim_time:=true']),
        'mapper': start(b, 'mapper', [_exe('rfm_mapper_node', 'mapper'), '--ros-args', '-p', 'use_sim_time:=true',
                                      '-p', f'map_path:={map_path}']),
        'detector': start(a, 'detector', [_exe('rfm_detector_node', 'detector'), '--ros-args',
                                          '-p', 'use_sim_time:=true', *remaps]),
    }
    try:
        time.sleep(8)                                       # the nodes load their models
        for name, p in procs.items():
            assert p.poll() is None, (tmp_path / f'{name}.log').read_text()[-2000:]
        play = subprocess.run(['ip', 'netns', 'exec', a, shutil.which('rfm'), 'play', str(bag), '--delay', '1',
                               '--quiet', '--wait-for', *[BAG_REMAPS[k] for k in ('rgb/image', 'rgb/camera_info',
                                                                                  'depth/image', 'imu')]],
                              env=env, capture_output=True, text=True, timeout=180)
        assert play.returncode == 0, play.stdout[-2000:] + play.stderr[-2000:]
        time.sleep(6)                                       # the last keyframes solve
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for name, p in procs.items():
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs.values():
            f.close()
    log = (tmp_path / 'mapper.log').read_text()
    assert map_path.is_file(), log[-3000:]                 # saved by the mapper as it stopped
    mapper = Mapper()
    load_map(mapper, map_path)
    result = evaluate_run(mapper, read_ground_truth(bag))
    loc, m = result['localization'], result['mapping']
    print(json.dumps({'keyframes': len(mapper.keyframes), 'registered': len(mapper.poses),
                      'ARE': loc['ARE_median'], 'ATE': loc['ATE_median'], 'localized': loc['registered'],
                      'AP25': m['AP25']}))
    # (keyframes held: in the map or culled into one of its keyframes)
    assert len(mapper.keyframes) + len(mapper.merged) >= 8 and len(mapper.poses) >= 0.7 * len(mapper.keyframes)
    # measured (3 runs, 2026-12-05): 100% localized, ATE 0.63 cm, AP25 0.72; bounds with room for
    # a slower machine, tight enough that a regression shows
    assert loc['registered'] >= 0.9 and loc['ATE_median'] < 0.02 and m['AP25'] > 0.5, (loc, m)
