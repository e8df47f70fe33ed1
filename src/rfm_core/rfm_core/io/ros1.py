"""ROS 1 bags (rosbag format 2.0: TUM RGB-D's sequences, most recordings made before ROS 2)
as rosbag2, so that ``rfm run --bag`` and ``rfm convert`` take them like any other bag.

Each message migrates to its ROS 2 definition (``rosbags``: ``std_msgs/Header`` loses
``seq``, ``tf/tfMessage`` becomes ``tf2_msgs/TFMessage``); topics keep their names; a
topic whose type ROS 2 does not know is left out and named. Frame names lose a leading
``/`` (ROS 2's tf2 refuses them). An IMU topic whose angular velocity is zero in every
message is an accelerometer alone (the Kinect's, in TUM's bags) and is marked so, as REP 145
asks (``angular_velocity_covariance[0] = -1``): else its zeros would read as a camera that
never turns. With ``ground_truth_tf`` (a world frame and the camera's
frame, e.g. TUM's ``world`` and ``openni_rgb_optical_frame``) the bag's own ``/tf`` — a
motion-capture system's, as TUM records it — gives the camera's true pose at each colour
image, levelled about the accelerometer's gravity (:func:`~rfm_core.io.datasets.level_ground_truth`),
on ``/ground_truth/camera_pose``: the run's report scores against it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ['is_ros1_bag', 'ros1_topics', 'ros1_to_rosbag2']

_MAGIC = b'#ROSBAG V2.0\n'


def is_ros1_bag(path) -> bool:
    """Whether ``path`` is a ROS 1 bag file."""
    path = Path(path)
    try:
        with open(path, 'rb') as f:
            return path.is_file() and f.read(len(_MAGIC)) == _MAGIC
    except OSError:
        return False


def _reading():
    """The errors reading a ROS 1 bag can raise, and what they become (ValueError)."""
    from rosbags.highlevel import AnyReaderError  # noqa: PLC0415
    from rosbags.rosbag1 import ReaderError  # noqa: PLC0415

    return (AnyReaderError, ReaderError, OSError, KeyError)


def ros1_topics(src) -> dict:
    """{topic: message type} of a ROS 1 bag; ValueError for one that cannot be read."""
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    try:
        with AnyReader([Path(src)]) as reader:
            return {c.topic: c.msgtype for c in reader.connections}
    except _reading() as exc:
        raise ValueError(f'{src} cannot be read as a ROS 1 bag ({type(exc).__name__}: {exc})') from None


def _frame(name: str) -> str:
    return name.lstrip('/')


def _ground_truth(reader, connections, world: str, camera: str, colour: str, imu: str) -> tuple[list, float]:
    """([(stamp_ns, 4x4 T_world_camera)] at the colour images, levelled; the turn in degrees)."""
    from rfm_core.io.datasets import level_ground_truth  # noqa: PLC0415
    from rfm_core.io.messages import stamp_to_ns, transforms_from_msg  # noqa: PLC0415
    from rfm_core.transforms import TransformBuffer  # noqa: PLC0415

    buffer = TransformBuffer(cache_s=1e9, tolerance_s=0.0)
    stamps, imu_stamps, accel = [], [], []
    wanted = [c for c in connections if c.topic in ('/tf', '/tf_static', colour, imu)]
    for conn, _, raw in reader.messages(connections=wanted):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.topic in ('/tf', '/tf_static'):
            for parent, child, stamp_ns, matrix in transforms_from_msg(msg):
                buffer.add(_frame(parent), _frame(child), stamp_ns, matrix, static=conn.topic == '/tf_static')
        elif conn.topic == colour:
            stamps.append(stamp_to_ns(msg.header.stamp))
        else:
            a = msg.linear_acceleration
            imu_stamps.append(stamp_to_ns(msg.header.stamp))
            accel.append([a.x, a.y, a.z])
    truth = [(s, m) for s in stamps if (m := buffer.lookup(world, camera, s)) is not None]
    if not truth:
        raise ValueError(f'no transform {world} -> {camera} in the bag\'s /tf at its colour images (frames: '
                         f'{", ".join(sorted(set(buffer.links) | {link.parent for link in buffer.links.values()}))})')
    return level_ground_truth(truth, np.array(imu_stamps, np.int64), np.array(accel).reshape(-1, 3))


def ros1_to_rosbag2(src, dst, ground_truth_tf: tuple[str, str] | None = None, colour: str = '/camera/rgb/image_color',
                    imu: str = '/imu') -> dict:
    """Write the ROS 1 bag ``src`` as a rosbag2 MCAP directory ``dst`` (must not exist); see
    the module. ``colour`` and ``imu``: the topics the ground truth is sampled at and levelled
    with. Returns {'topics': {topic: msgtype}, 'left_out': {topic: msgtype}, 'messages',
    'ground_truth', 'levelled_deg'}; ValueError for a bag it cannot read or ground truth it
    cannot find."""
    from rosbags.convert.converter import STATIC_MSGTYPE_RENAMES, generate_message_converter  # noqa: PLC0415
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    from rfm_core.io.bag import BagWriter  # noqa: PLC0415
    from rfm_core.io.messages import pose_stamped_msg  # noqa: PLC0415
    from rfm_core.io.topics import GROUND_TRUTH_TOPICS  # noqa: PLC0415

    src, dst = Path(src), Path(dst)
    out = {'topics': {}, 'left_out': {}, 'messages': 0, 'ground_truth': 0, 'levelled_deg': 0.0}
    try:
        with AnyReader([src]) as reader, BagWriter(dst) as bag:
            truth, out['levelled_deg'] = (_ground_truth(reader, reader.connections, *map(_frame, ground_truth_tf),
                                                        colour, imu) if ground_truth_tf else ([], 0.0))
            cache: dict = {}
            convert = {}
            for conn in reader.connections:
                msgtype = STATIC_MSGTYPE_RENAMES.get(conn.msgtype, conn.msgtype)
                if msgtype not in bag.typestore.fielddefs:
                    out['left_out'][conn.topic] = conn.msgtype
                    continue
                if conn.topic not in out['topics']:
                    latched = bool(getattr(conn.ext, 'latching', 0)) or conn.topic == '/tf_static'
                    bag.add_topic(conn.topic, msgtype, latched=latched)
                    out['topics'][conn.topic] = msgtype
                convert[conn.id] = (msgtype, generate_message_converter(
                    reader.typestore, bag.typestore, conn.msgtype, msgtype, cache, src_is2=False, dst_is2=True))
            if truth:
                bag.add_topic(GROUND_TRUTH_TOPICS['gt_pose'], 'geometry_msgs/msg/PoseStamped')
            strip: dict = {}                      # connection id -> whether its frame names need a fix
            no_gyroscope = _accelerometers(reader, [c for c in reader.connections if c.id in convert
                                                    and convert[c.id][0] == 'sensor_msgs/msg/Imu'])
            pending = iter(truth)
            upcoming = next(pending, None)
            for conn, stamp, raw in reader.messages(connections=[c for c in reader.connections if c.id in convert]):
                while upcoming is not None and upcoming[0] <= stamp:
                    bag.write(GROUND_TRUTH_TOPICS['gt_pose'], upcoming[0],
                              pose_stamped_msg(upcoming[1], upcoming[0], 'map', bag.make))
                    out['ground_truth'] += 1
                    upcoming = next(pending, None)
                msgtype, migrate = convert[conn.id]
                data = bytes(migrate(raw))
                if conn.id in no_gyroscope:
                    imu_msg = bag.typestore.deserialize_cdr(data, msgtype)
                    imu_msg.angular_velocity_covariance = np.r_[-1.0, imu_msg.angular_velocity_covariance[1:]]
                    data = bag.typestore.serialize_cdr(imu_msg, msgtype)
                if strip.get(conn.id, True):      # (decided by a connection's first message, but /tf's each)
                    stripped = _strip_frames(bag.typestore, data, msgtype)
                    strip[conn.id] = stripped is not data or msgtype == 'tf2_msgs/msg/TFMessage'
                    data = stripped
                bag.write_raw(conn.topic, stamp, data)
                out['messages'] += 1
            for s, m in ([upcoming] if upcoming is not None else []) + list(pending):
                bag.write(GROUND_TRUTH_TOPICS['gt_pose'], s, pose_stamped_msg(m, s, 'map', bag.make))
                out['ground_truth'] += 1
    except _reading() as exc:
        raise ValueError(f'{src} cannot be read as a ROS 1 bag ({type(exc).__name__}: {exc})') from None
    return out


def _accelerometers(reader, connections) -> set:
    """Ids of the IMU connections whose every message reads zero angular velocity."""
    zero = {c.id for c in connections}
    for conn, _, raw in (reader.messages(connections=connections) if connections else ()):
        if conn.id in zero:
            w = reader.deserialize(raw, conn.msgtype).angular_velocity
            if w.x or w.y or w.z:
                zero.discard(conn.id)
    return zero


def _strip_frames(typestore, data: bytes, msgtype: str) -> bytes:
    """The message with every ``frame_id`` / ``child_frame_id`` that starts with ``/`` without it."""
    msg = typestore.deserialize_cdr(data, msgtype)
    changed = [False]

    def visit(m):
        for name in getattr(m, '__dataclass_fields__', {}):
            value = getattr(m, name)
            if name in ('frame_id', 'child_frame_id') and isinstance(value, str) and value.startswith('/'):
                setattr(m, name, _frame(value))
                changed[0] = True
            elif hasattr(value, '__dataclass_fields__'):
                visit(value)
            elif isinstance(value, list):
                for item in value:
                    visit(item)

    visit(msg)
    return typestore.serialize_cdr(msg, msgtype) if changed[0] else data
