"""RGB-D dataset folders (TUM RGB-D and the generic layout) as bags: fixtures written here from
a rendered capture, converted, read back and compared with what was rendered."""
import numpy as np
import pytest

from rfm_core.io.datasets import level_ground_truth, parse_axes, read_folder, write_bag
from rfm_core.sim.capture import Capture, CaptureConfig
from rfm_core.sim.trajectory import imu_samples

PIL = pytest.importorskip('PIL.Image')

# the motion-capture frame of the fixture: tilted 20 deg about x and shifted (z is not up)
_TILT = np.eye(4)
_TILT[:3, :3] = np.array([[1, 0, 0], [0, np.cos(0.35), -np.sin(0.35)], [0, np.sin(0.35), np.cos(0.35)]])
_TILT[:3, 3] = (1.0, -2.0, 0.5)
# the fixture's IMU axes, as a file would store them: file = R^T optical with R = parse_axes('-y,x,z')
_AXES = '-y,x,z'


def _seconds(ns: int) -> str:
    return f'{ns // 10**9}.{ns % 10**9:09d}'


def _quaternion(r):
    w = np.sqrt(max(1.0 + np.trace(r), 1e-12)) / 2
    return np.array([(r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w), w])


def write_fixture(root, layout: str, frames: int = 6, seed: int = 3):
    """A folder of a rendered capture in ``layout`` ('tum': 5000 per metre, accelerometer
    only, TUM's file names; 'generic': camera.yaml, millimetres, imu.txt with the gyroscope),
    depth stamped 7 ms after colour, ground truth in a tilted frame. Returns the capture's
    frames and IMU."""
    cap = Capture(CaptureConfig(seed=seed, frames=frames, fps=5))
    rendered = list(cap.frames())
    (root / 'rgb').mkdir(parents=True)
    (root / 'depth').mkdir()
    scale = 5000.0 if layout == 'tum' else 1000.0
    rgb_lines, depth_lines, truth_lines = ['# colour images'], ['# depth images'], ['# timestamp tx ty tz qx qy qz qw']
    for f in rendered:
        name = _seconds(f.stamp_ns)
        PIL.fromarray(f.render.rgb).save(root / 'rgb' / f'{name}.png')
        depth = np.where(np.isfinite(f.render.depth), np.rint(f.render.depth * scale), 0).astype(np.uint16)
        PIL.fromarray(depth).save(root / 'depth' / f'{name}.png')
        rgb_lines.append(f'{name} rgb/{name}.png')
        depth_lines.append(f'{_seconds(f.stamp_ns + 7_000_000)} depth/{name}.png')
        pose = _TILT @ f.pose_matrix
        truth_lines.append(f'{name} ' + ' '.join(f'{v:.9f}' for v in np.r_[pose[:3, 3], _quaternion(pose[:3, :3])]))
    (root / 'rgb.txt').write_text('\n'.join(rgb_lines) + '\n')
    (root / 'depth.txt').write_text('\n'.join(depth_lines) + '\n')
    (root / 'groundtruth.txt').write_text('\n'.join(truth_lines) + '\n')
    imu = imu_samples(cap.trajectory, 100.0, seed=1)
    stamps = [cap.stamp_ns(t) for t in imu.times]
    to_file = parse_axes(_AXES).T                           # optical -> the file's axes
    accel = imu.linear_acceleration @ to_file.T
    gyro = imu.angular_velocity @ to_file.T
    if layout == 'tum':
        rows = [f'{_seconds(s)} {a[0]:.6f} {a[1]:.6f} {a[2]:.6f}' for s, a in zip(stamps, accel)]
        (root / 'accelerometer.txt').write_text('# timestamp ax ay az\n' + '\n'.join(rows) + '\n')
    else:
        rows = [f'{_seconds(s)} ' + ' '.join(f'{v:.6f}' for v in np.r_[a, w]) for s, a, w in zip(stamps, accel, gyro)]
        (root / 'imu.txt').write_text('\n'.join(rows) + '\n')
        k = cap.intrinsics
        (root / 'camera.yaml').write_text(f'fx: {k.fx}\nfy: {k.fy}\ncx: {k.cx}\ncy: {k.cy}\ndepth_scale: 1000\n'
                                          f"accel_axes: '{_AXES}'\n")
    return cap, rendered, imu


def _read_bag(path):
    from rosbags.highlevel import AnyReader

    from rfm_core.io.bag import rfm_typestore

    out = {}
    with AnyReader([path], default_typestore=rfm_typestore()) as reader:
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    return out


@pytest.mark.parametrize('layout', ['tum', 'generic'])
def test_a_dataset_folder_becomes_a_bag_of_what_was_rendered(tmp_path, layout):
    from rfm_core.io.images import depth_to_meters, image_to_rgb
    from rfm_core.io.messages import pose_to_matrix

    name = 'rgbd_dataset_freiburg3_fixture' if layout == 'tum' else 'scan'
    cap, rendered, imu = write_fixture(tmp_path / name, layout)
    k = cap.intrinsics
    folder = read_folder(tmp_path / name, intrinsics=(k.fx, k.fy, k.cx, k.cy) if layout == 'tum' else None,
                         accel_axes=_AXES if layout == 'tum' else None)
    summary = write_bag(folder, tmp_path / 'bag')
    assert summary['frames'] == len(rendered) and summary['skipped'] == 0
    assert summary['gyroscope'] == (layout == 'generic')
    topics = _read_bag(tmp_path / 'bag')
    colour = topics['/camera/color/image_raw']
    depth = topics['/camera/depth/image_raw']
    assert [s for s, _ in colour] == [f.stamp_ns for f in rendered]
    assert [s for s, _ in depth] == [f.stamp_ns + 7_000_000 for f in rendered]       # its own stamp
    for f, (_, c), (_, d) in zip(rendered, colour, depth):
        assert np.array_equal(image_to_rgb(c), f.render.rgb)
        metres = depth_to_meters(d)
        valid = np.isfinite(f.render.depth) & (f.render.depth > 0)
        assert np.nanmax(np.abs(metres[valid] - f.render.depth[valid])) <= 0.0011      # 1 mm steps
    info = topics['/camera/color/camera_info'][0][1]
    assert np.allclose(np.asarray(info.k).reshape(3, 3), k.matrix) and (info.width, info.height) == (k.width, k.height)
    # the IMU in the camera optical frame, whatever axes the file used
    samples = topics['/imu/data']
    assert len(samples) == len(imu.times)
    accel = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for _, m in samples])
    assert np.allclose(accel, imu.linear_acceleration, atol=2e-6)
    gyro_cov = np.array([m.angular_velocity_covariance[0] for _, m in samples])
    if layout == 'tum':
        assert np.all(gyro_cov == -1)                     # no gyroscope (REP 145)
    else:
        assert np.all(gyro_cov > 0)
        gyro = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for _, m in samples])
        assert np.allclose(gyro, imu.angular_velocity, atol=2e-6)
    # ground truth levelled: z up again, and the same trajectory up to a turn about z and a shift
    truth = [pose_to_matrix(m.pose) for _, m in topics['/ground_truth/camera_pose']]
    assert abs(summary['levelled_deg'] - 20.05) < 0.3
    for got, f in zip(truth, rendered):
        assert np.degrees(np.arccos(np.clip(got[:3, :3][2] @ f.pose_matrix[:3, :3][2], -1, 1))) < 1.0
    rel_got = np.linalg.inv(truth[0]) @ truth[-1]
    rel_true = np.linalg.inv(rendered[0].pose_matrix) @ rendered[-1].pose_matrix
    assert np.allclose(rel_got, rel_true, atol=1e-5)


def test_tum_intrinsics_follow_the_camera_named_in_the_folder(tmp_path):
    write_fixture(tmp_path / 'rgbd_dataset_freiburg1_desk', 'tum', frames=2)
    assert read_folder(tmp_path / 'rgbd_dataset_freiburg1_desk').intrinsics == (517.3, 516.5, 318.6, 255.3)


def test_levelling_needs_the_accelerometer_and_leaves_a_level_frame_alone():
    level = np.eye(4)
    level[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]               # optical axes in a z-up world: looking along +y
    poses = [(10**9 * i, level) for i in range(3)]
    stamps = np.array([s for s, _ in poses])
    up = np.array([[0.0, -9.8, 0.0, np.nan, np.nan, np.nan]] * 3)    # at rest: optical y is down
    out, deg = level_ground_truth(poses, stamps, up)
    assert deg < 1e-6 and np.allclose(out[0][1], level)
    assert level_ground_truth(poses, stamps[:0], up[:0]) == (poses, 0.0)


def test_ground_truth_is_given_at_the_frames_stamps(tmp_path):
    root = tmp_path / 'rgbd_dataset_freiburg3_fixture'
    cap, rendered, _ = write_fixture(root, 'tum', frames=3)
    # a motion-capture rate of its own: two poses 40 ms apart around each frame, none at it
    lines = []
    for f in rendered:
        for dt, x in ((-20_000_000, 0.0), (20_000_000, 0.4)):
            lines.append(f'{_seconds(f.stamp_ns + dt)} {x} 0 0 0 0 0 1')
    (root / 'groundtruth.txt').write_text('\n'.join(lines) + '\n')
    folder = read_folder(root)
    assert [s for s, _ in folder.ground_truth] == [f.stamp_ns for f in rendered]
    assert all(abs(m[0, 3] - 0.2) < 1e-9 for _, m in folder.ground_truth)


def test_a_broken_folder_says_what_is_wrong(tmp_path):
    with pytest.raises(FileNotFoundError, match='rgb.txt'):
        read_folder(tmp_path)
    root = tmp_path / 'generic'
    write_fixture(root, 'generic', frames=2)
    (root / 'camera.yaml').write_text('fx: 500\nfy: 500\ncx: 160\n')
    with pytest.raises(ValueError, match='missing cy, depth_scale'):
        read_folder(root)
    (root / 'camera.yaml').write_text('fx: 500\nfy: 500\ncx: 160\ncy: 120\ndepth_scale: 1000\naccel_axes: x,x,z\n')
    with pytest.raises(ValueError, match='repeats an axis'):
        read_folder(root)
    (root / 'camera.yaml').write_text('fx: 500\nfy: 500\ncx: 160\ncy: 120\ndepth_scale: 1000\n')
    (root / 'groundtruth.txt').write_text('1.0 0 0 0 0 0 0 2\n')
    with pytest.raises(ValueError, match='quaternion of norm 2'):
        read_folder(root)
    (root / 'groundtruth.txt').unlink()
    (root / 'imu.txt').write_text('1.0 0 9.8\n')
    with pytest.raises(ValueError, match='imu.txt:1: expected 4 or 7 numbers'):
        read_folder(root)


@pytest.mark.slow
@pytest.mark.ros
def test_a_tum_folder_runs_through_the_graph_and_is_scored(tmp_path):
    """`rfm convert` then `rfm run --bag`: the depth detector, gravity from the accelerometer
    alone, the report scored against the folder's (levelled, interpolated) ground truth."""
    import json
    import shutil
    import subprocess

    pytest.importorskip('rclpy')
    root = tmp_path / 'rgbd_dataset_freiburg3_walk'
    cap, rendered, _ = write_fixture(root, 'tum', frames=40)
    k = cap.intrinsics
    rfm = shutil.which('rfm')
    convert = subprocess.run([rfm, 'convert', str(root), '--output', str(tmp_path / 'bag'), f'--accel-axes={_AXES}',
                              '--intrinsics', *map(str, (k.fx, k.fy, k.cx, k.cy)), '--quiet'],
                             capture_output=True, text=True, timeout=120)
    assert convert.returncode == 0, convert.stderr[-3000:]
    assert 'accelerometer only' in convert.stdout and 'levelled by 20.' in convert.stdout, convert.stdout
    run = subprocess.run([rfm, 'run', '--bag', str(tmp_path / 'bag'), '--output', str(tmp_path / 'out'),
                          '--no-processes', '--quiet', '--settle', '2'], capture_output=True, text=True, timeout=240)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    loc = json.loads((tmp_path / 'out' / 'summary.json').read_text())['accuracy']['localization']
    assert loc['registered'] >= 0.8 and loc['gross'] == 0, loc
    assert loc['ATE_median'] < 0.05 and loc['ARE_median'] < 2.0, loc
    assert 'the map is not scored' in (tmp_path / 'out' / 'report.md').read_text()


def write_ros1_bag(path, frames: int = 40, seed: int = 3):
    """A ROS 1 bag as TUM RGB-D records one, of a rendered capture: rgb8 colour, 32FC1 depth in
    metres, camera_info, the Kinect's accelerometer on /imu (angular velocity zero, nothing saying
    there is no gyroscope), and the
    motion capture on /tf (tf/tfMessage, frames with a leading slash: /world -> /kinect at 100 Hz,
    /kinect -> /openni_rgb_optical_frame), the world tilted (z not up). Returns the capture's frames."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg('geometry_msgs/TransformStamped[] transforms', 'tf/msg/tfMessage'))
    t = store.types
    cap = Capture(CaptureConfig(seed=seed, frames=frames, fps=5))
    rendered = list(cap.frames())
    imu = imu_samples(cap.trajectory, 100.0, seed=1)
    mount = np.eye(4)
    mount[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])        # body (x forward) -> optical
    mount[:3, 3] = (0.02, -0.05, 0.1)

    def stamp(ns):
        return t['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9)

    def head(ns, frame, seq=0):
        return t['std_msgs/msg/Header'](seq=seq, stamp=stamp(ns), frame_id=frame)

    def transform(parent, child, ns, m):
        q = _quaternion(m[:3, :3])
        return t['geometry_msgs/msg/TransformStamped'](
            header=head(ns, parent), child_frame_id=child, transform=t['geometry_msgs/msg/Transform'](
                translation=t['geometry_msgs/msg/Vector3'](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                rotation=t['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3])))

    k = cap.intrinsics
    info = dict(height=k.height, width=k.width, distortion_model='plumb_bob', D=np.zeros(5),
                K=np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1.0]), R=np.eye(3).reshape(-1),
                P=np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
                roi=t['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    events = [(f.stamp_ns, 'frame', f) for f in rendered]
    events += [(cap.stamp_ns(s), 'imu', a) for s, a in zip(imu.times, imu.linear_acceleration)]
    events.sort(key=lambda e: e[0])
    optical = '/openni_rgb_optical_frame'
    with Writer(path) as bag:
        conns = {name: bag.add_connection(name, kind, typestore=store) for name, kind in (
            ('/camera/rgb/image_color', 'sensor_msgs/msg/Image'), ('/camera/depth/image', 'sensor_msgs/msg/Image'),
            ('/camera/rgb/camera_info', 'sensor_msgs/msg/CameraInfo'), ('/imu', 'sensor_msgs/msg/Imu'),
            ('/tf', 'tf/msg/tfMessage'))}

        def write(topic, ns, msg):
            bag.write(conns[topic], ns, store.serialize_ros1(msg, conns[topic].msgtype))

        for ns, kind, item in events:
            if kind == 'imu':
                zero = t['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0)
                write('/imu', ns, t['sensor_msgs/msg/Imu'](
                    header=head(ns, optical), orientation=t['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.r_[-1.0, np.zeros(8)], angular_velocity=zero,
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=t['geometry_msgs/msg/Vector3'](x=item[0], y=item[1], z=item[2]),
                    linear_acceleration_covariance=np.zeros(9)))
                continue
            f = item
            write('/tf', ns, t['tf/msg/tfMessage'](transforms=[
                transform('/world', '/kinect', ns, _TILT @ f.pose_matrix @ np.linalg.inv(mount)),
                transform('/kinect', optical, ns, mount)]))
            rgb = np.ascontiguousarray(f.render.rgb, np.uint8)
            write('/camera/rgb/image_color', ns, t['sensor_msgs/msg/Image'](
                header=head(ns, optical), height=rgb.shape[0], width=rgb.shape[1], encoding='rgb8', is_bigendian=0,
                step=3 * rgb.shape[1], data=rgb.reshape(-1)))
            depth = np.where(np.isfinite(f.render.depth), f.render.depth, np.nan).astype('<f4')
            write('/camera/depth/image', ns + 7_000_000, t['sensor_msgs/msg/Image'](
                header=head(ns + 7_000_000, optical), height=depth.shape[0], width=depth.shape[1], encoding='32FC1',
                is_bigendian=0, step=4 * depth.shape[1], data=depth.view(np.uint8).reshape(-1)))
            write('/camera/rgb/camera_info', ns, t['sensor_msgs/msg/CameraInfo'](header=head(ns, optical), **info))
    return rendered


def test_a_tum_ros1_bag_runs_through_the_graph_and_is_scored(tmp_path):
    """`rfm run --bag x.bag`: a ROS 1 bag converted on the way in (TUM's topics found, frames
    without their leading slash, tf/tfMessage as tf2_msgs/TFMessage), gravity from an
    accelerometer alone, the ground truth from the bag's /tf when its frames are named."""
    import json
    import shutil
    import subprocess

    pytest.importorskip('rclpy')
    rendered = write_ros1_bag(tmp_path / 'rgbd_dataset_freiburg3_walk.bag')
    rfm = shutil.which('rfm')
    run = subprocess.run([rfm, 'run', '--bag', str(tmp_path / 'rgbd_dataset_freiburg3_walk.bag'), '--output',
                          str(tmp_path / 'out'), '--ground-truth-tf', 'world:openni_rgb_optical_frame',
                          '--no-processes', '--quiet', '--settle', '2'], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "TUM RGB-D's topics" in run.stdout and 'levelled by 20.' in run.stdout, run.stdout
    converted = _read_bag(tmp_path / 'out' / 'input')
    assert len(converted['/camera/rgb/image_color']) == len(rendered) == len(converted['/ground_truth/camera_pose'])
    assert all(m.angular_velocity_covariance[0] == -1 for _, m in converted['/imu'])    # an accelerometer alone
    tf = converted['/tf'][0][1]
    assert {(x.header.frame_id, x.child_frame_id) for x in tf.transforms} == {
        ('world', 'kinect'), ('kinect', 'openni_rgb_optical_frame')}
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    loc = summary['accuracy']['localization']
    assert loc['registered'] >= 0.8 and loc['gross'] == 0, loc
    assert loc['ATE_median'] < 0.05 and loc['ARE_median'] < 2.0, loc
    for name in ('trajectory.tum', 'map.rfm', 'report.md', 'top_down.png', 'objects.json'):
        assert (tmp_path / 'out' / name).is_file(), name
    bad = subprocess.run([rfm, 'run', '--bag', str(tmp_path / 'rgbd_dataset_freiburg3_walk.bag'), '--output',
                          str(tmp_path / 'bad'), '--ground-truth-tf', 'world:nowhere', '--quiet'],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and 'no transform world -> nowhere' in bad.stderr, bad.stderr[-2000:]
    (tmp_path / 'broken.bag').write_bytes(b'#ROSBAG V2.0\n' + bytes(range(256)) * 4)
    broken = subprocess.run([rfm, 'run', '--bag', str(tmp_path / 'broken.bag'), '--output', str(tmp_path / 'broken'),
                             '--quiet'], capture_output=True, text=True, timeout=120)
    assert broken.returncode != 0 and 'cannot be read as a ROS 1 bag' in broken.stderr, broken.stderr[-2000:]
