"""The ROS-free TF tree: lookups along chains, interpolation in time, one parent per frame,
and where the map attaches (REP 105)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rfm_core.transforms import TransformBuffer, map_attachment

S = 10**9


def rigid(rng, scale=1.0):
    m = np.eye(4)
    m[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    m[:3, 3] = rng.normal(0, scale, 3)
    return m


def yaw_at(x, yaw_deg):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler('z', yaw_deg, degrees=True).as_matrix()
    m[0, 3] = x
    return m


def robot_tree(rng):
    """odom -> base_link (driving: 1 m/s along x, 10 deg/s), base_link -> camera_link ->
    optical (static, a mount 0.4 m up)."""
    buf = TransformBuffer(cache_s=30.0)
    mount, optical = np.eye(4), rigid(rng, 0.02)
    mount[:3, 3] = (0.1, 0.0, 0.4)
    buf.add('base_link', 'camera_link', 0, mount, static=True)
    buf.add('camera_link', 'optical', 0, optical, static=True)
    for i in range(11):
        buf.add('odom', 'base_link', i * S, yaw_at(float(i), 10.0 * i))
    return buf, mount @ optical


def test_lookups_compose_along_the_tree_both_ways():
    rng = np.random.default_rng(0)
    buf = TransformBuffer()
    a, b, c = rigid(rng), rigid(rng), rigid(rng)
    buf.add('world', 'x', 0, a, static=True)
    buf.add('x', 'y', 0, b, static=True)
    buf.add('world', 'z', 0, c, static=True)
    assert np.allclose(buf.lookup('world', 'y', 5 * S), a @ b)
    assert np.allclose(buf.lookup('z', 'y', 5 * S), np.linalg.inv(c) @ a @ b)
    assert np.allclose(buf.lookup('y', 'z', 5 * S), np.linalg.inv(a @ b) @ c)
    assert np.allclose(buf.lookup('y', 'y', 0), np.eye(4))
    assert buf.lookup('world', 'elsewhere', 0) is None
    assert buf.root('y') == 'world' and buf.parent('y') == 'x'


def test_moving_frames_are_interpolated_and_never_extrapolated_far():
    buf, _ = robot_tree(np.random.default_rng(1))
    mid = buf.lookup('odom', 'base_link', int(2.5 * S))
    assert np.allclose(mid[:3, 3], (2.5, 0.0, 0.0))
    assert np.isclose(Rotation.from_matrix(mid[:3, :3]).as_euler('zyx', degrees=True)[0], 25.0)
    assert np.allclose(buf.lookup('odom', 'base_link', 10 * S + 10**7)[:3, 3], (10.0, 0, 0))   # 10 ms late: the last
    assert buf.lookup('odom', 'base_link', 10 * S + 10**7, exact=True) is None                 # ... unless exact
    assert np.allclose(buf.lookup('odom', 'base_link', int(2.5 * S), exact=True), mid)
    assert buf.lookup('odom', 'base_link', 11 * S) is None                                    # a second late: nothing
    assert buf.lookup('odom', 'optical', -S) is None


def test_a_second_parent_a_loop_and_a_broken_transform_are_refused():
    buf, _ = robot_tree(np.random.default_rng(2))
    assert 'second one' in buf.add('map', 'base_link', 0, np.eye(4))
    assert 'ancestor' in buf.add('optical', 'odom', 0, np.eye(4))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    assert 'rigid' in buf.add('base_link', 'laser', 0, bad)
    assert buf.parent('base_link') == 'odom' and buf.parent('odom') is None and 'laser' not in buf.links


def test_old_transforms_leave_the_cache():
    buf = TransformBuffer(cache_s=2.0)
    for i in range(10):
        buf.add('odom', 'base_link', i * S, yaw_at(float(i), 0.0))
    assert buf.links['base_link'].stamps == [7 * S, 8 * S, 9 * S]
    assert buf.lookup('odom', 'base_link', 3 * S) is None


def test_a_link_whose_time_goes_back_starts_again():
    """A bag that loops (or a simulator that restarts) sends its first stamps again: the
    odometry is looked up on the new pass (kept beside the old one, each new transform was
    cut at once and the robot had no odometry until the new pass caught up), while a
    transform a little out of order is still kept, and the static mount stays."""
    buf = TransformBuffer(cache_s=5.0)
    mount = yaw_at(0.1, 0.0)
    buf.add('base_link', 'camera_link', 0, mount, static=True)
    for i in range(11):
        buf.add('odom', 'base_link', i * S, yaw_at(float(i), 10.0 * i))
    buf.add('odom', 'base_link', 9 * S + S // 2, yaw_at(9.5, 95.0))            # out of order, within the cache
    np.testing.assert_allclose(buf.lookup('odom', 'base_link', 9 * S + S // 2)[0, 3], 9.5)
    for i in range(2):                                                          # the bag again, 2 m further on
        buf.add('odom', 'base_link', i * S, yaw_at(float(i) + 2.0, 10.0 * i))
    assert buf.links['base_link'].stamps == [0, S]
    np.testing.assert_allclose(buf.lookup('odom', 'camera_link', S // 2), yaw_at(2.5, 5.0) @ mount, atol=1e-9)


@pytest.mark.parametrize('tree', ['none', 'mount', 'robot'])
def test_the_map_hangs_from_the_root_of_the_cameras_tree(tree):
    rng = np.random.default_rng(3)
    camera_to_map = rigid(rng)
    stamp = int(4.5 * S)
    if tree == 'robot':
        buf, base_to_optical = robot_tree(rng)
    else:
        buf = TransformBuffer()
        if tree == 'mount':
            buf.add('camera_link', 'optical', 0, rigid(rng, 0.02), static=True)
    at = map_attachment(buf, camera_to_map, 'optical', stamp, 'map')
    assert at.child == {'none': 'optical', 'mount': 'camera_link', 'robot': 'odom'}[tree]
    assert at.held == (tree == 'robot')                 # map -> odom moves with the odometry's drift
    below = np.eye(4) if tree == 'none' else buf.lookup(at.child, 'optical', stamp)
    assert np.allclose(at.matrix @ below, camera_to_map)     # the camera lands where the mapper put it
    buf.add('map', at.child, stamp, at.matrix)               # broadcast: the tree stays a tree
    assert buf.root('optical') == 'map'
    again = map_attachment(buf, camera_to_map, 'optical', stamp, 'map')    # its own broadcast heard back
    assert again.child == at.child and np.allclose(again.matrix, at.matrix)


def test_the_map_attaches_to_odom_below_a_root_of_its_own():
    """A tree whose root is above odom (a 'world' frame another node keeps): map -> odom
    would give odom a second parent, so nothing is broadcast; without that parent, odom."""
    rng = np.random.default_rng(5)
    buf, _ = robot_tree(rng)
    at = map_attachment(buf, rigid(rng), 'optical', 3 * S, 'map')
    assert at.child == 'odom'
    buf.add('world', 'odom', 0, np.eye(4), static=True)
    assert 'odom already has the parent world' in map_attachment(buf, rigid(rng), 'optical', 3 * S, 'map')


def test_no_map_to_odom_without_odometry_near_the_image():
    buf, _ = robot_tree(np.random.default_rng(4))
    why = map_attachment(buf, np.eye(4), 'optical', 20 * S, 'map')
    assert isinstance(why, str) and 'odom -> optical' in why


def test_a_frames_acceleration_from_its_positions_over_time():
    """A base speeding up along x at 0.8 m/s^2 (odometry every 20 ms): the optical frame's
    acceleration in odom, in its own axes, is the base's (the mount is static); the newest
    moment /tf has the chain is the last odometry; nothing before two steps of odometry."""
    rng = np.random.default_rng(3)
    buf = TransformBuffer(cache_s=30.0)
    optical = rigid(rng, 0.02)
    buf.add('base_link', 'optical', 0, optical, static=True)
    assert buf.newest('odom', 'optical') is None                  # not connected yet
    step = S // 50
    for i in range(51):
        t = i * step / S
        buf.add('odom', 'base_link', i * step, yaw_at(0.4 * t * t, 0.0))
    assert buf.newest('odom', 'optical') == 50 * step
    assert buf.newest('base_link', 'optical') is None             # static all the way
    found = buf.acceleration('odom', 'optical', 40 * step, 3 * step)
    np.testing.assert_allclose(found, optical[:3, :3].T @ [0.8, 0.0, 0.0], atol=1e-6)
    assert buf.acceleration('odom', 'optical', step, step) is None    # the odometry begins at 0
