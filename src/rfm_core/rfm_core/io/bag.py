"""rosbag2 (MCAP) writing and reading without ROS, on the ``rosbags`` library.

Bags written here are ordinary rosbag2 directories (``metadata.yaml`` + one ``.mcap``
file, zstd-compressed chunks) that ``ros2 bag``, Foxglove, ``rosbags`` and the ``mcap``
reader all open. Custom rfm types are registered from the ``.msg`` files of rfm_msgs and
embedded in the bag, so readers need no rfm install.
"""
from __future__ import annotations

import os
from pathlib import Path

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from rfm_core.io.messages import BagMessages

__all__ = ['rfm_msgs_dir', 'rfm_typestore', 'BagWriter', 'qos_profile', 'bag_custom_data', 'topic_messages']

_INFINITE = QosTime(0x7FFFFFFF, 0xFFFFFFFF)


def rfm_msgs_dir() -> Path:
    """Directory with the rfm_msgs ``.msg`` files: the installed share/ or the source tree."""
    for prefix in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        candidate = Path(prefix) / 'share' / 'rfm_msgs' / 'msg'
        if prefix and candidate.is_dir():
            return candidate
    source = Path(__file__).resolve().parents[3] / 'rfm_msgs' / 'msg'
    if source.is_dir():
        return source
    raise FileNotFoundError('cannot find the rfm_msgs .msg files: build the workspace '
                            '(make setup) and source ros_ws/env.sh')


def rfm_typestore():
    """A ROS 2 Jazzy typestore that also knows the rfm_msgs types."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted(rfm_msgs_dir().glob('*.msg')):
        types.update(get_types_from_msg(path.read_text(), f'rfm_msgs/msg/{path.stem}'))
    store.register(types)
    return store


def qos_profile(latched: bool = False, reliable: bool = True, depth: int = 10) -> Qos:
    """The offered QoS recorded for a topic (latched = transient local, as for /tf_static)."""
    return Qos(QosHistory.KEEP_LAST, 1 if latched else depth,
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)


class BagWriter:
    """Write messages built with :attr:`make` to a new rosbag2 MCAP bag directory.

    ``with BagWriter(path) as bag: bag.add_topic(...); bag.write(topic, stamp_ns, msg)``
    """

    def __init__(self, path, compress: bool = True, compression_level: int = 10):
        self.path = Path(path)
        self.compression_level = compression_level
        self.typestore = rfm_typestore()
        self.make = BagMessages(self.typestore)
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections: dict = {}

    def __enter__(self) -> 'BagWriter':
        self._writer.open()
        storage = getattr(self._writer, 'storage', None)
        if getattr(storage, 'compression', '') == 'zstd':
            # rosbags compresses MCAP chunks at zstd's default level 3; images and depth
            # shrink by a further ~20% at level 10 for ~1 s per 30 MB.
            try:
                from compression import zstd  # noqa: PLC0415 - Python >= 3.14
            except ImportError:
                from backports import zstd  # noqa: PLC0415
            level = self.compression_level
            storage.compressor = lambda data: zstd.compress(data, level=level)
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def set_metadata(self, key: str, value: str) -> None:
        """A string stored in metadata.yaml's custom_data (e.g. how the bag was made)."""
        self._writer.set_custom_data(key, value)

    def add_topic(self, topic: str, msgtype: str, latched: bool = False,
                  reliable: bool = True) -> None:
        self._connections[topic] = (self._writer.add_connection(
            topic, msgtype, typestore=self.typestore,
            offered_qos_profiles=[qos_profile(latched, reliable)]), msgtype)

    def write(self, topic: str, stamp_ns: int, msg) -> None:
        """Serialise a message built with :attr:`make` and write it."""
        connection, msgtype = self._connections[topic]
        self._writer.write(connection, int(stamp_ns), self.typestore.serialize_cdr(msg, msgtype))

    def write_raw(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """Write an already serialised (CDR) message."""
        self._writer.write(self._connections[topic][0], int(stamp_ns), data)


def bag_custom_data(path) -> dict:
    """The ``custom_data`` strings of a rosbag2 directory's metadata.yaml."""
    import yaml  # noqa: PLC0415

    with open(Path(path) / 'metadata.yaml') as f:
        info = yaml.safe_load(f)['rosbag2_bagfile_information']
    return dict(info.get('custom_data') or {})


def topic_messages(path, topic: str):
    """The deserialised messages of one topic of a bag (rosbag2 folder or file), in bag order;
    nothing when the bag has no such topic (``reader.messages(connections=[])`` would read
    every topic)."""
    for _, msg in topics_messages(path, (topic,)):
        yield msg


def topics_messages(path, topics):
    """(topic, deserialised message) of the given topics of a bag, in bag order, in one pass."""
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    with AnyReader([Path(path)], default_typestore=rfm_typestore()) as reader:
        conns = [c for c in reader.connections if c.topic in set(topics)]
        if conns:
            for conn, _, raw in reader.messages(connections=conns):
                yield conn.topic, reader.deserialize(raw, conn.msgtype)


def iter_camera_frames(path, color_topic: str, depth_topic: str | None, info_topic: str,
                       imu_topic: str | None = None, extra_topics=(), slop_ns: int = 50_000_000):
    """Read a bag in time order and yield, per synchronised colour image, a dict with the
    deserialised ``color``, ``info``, ``depth`` (when given), the IMU messages received
    since the previous frame (``imu``), and the message of each ``extra_topics`` (e.g.
    ground truth), keyed by topic. Colour, camera_info, depth and the extra topics are
    matched by approximate time, as the detector node matches them: each within
    ``slop_ns`` of the others (drivers stamp depth a few ms after colour). At most four
    synchronised topics (colour, info, depth and one extra, or colour, info and two extras).
    """
    from rosbags.highlevel import AnyReader  # noqa: PLC0415

    from rfm_core.io.messages import stamp_to_ns  # noqa: PLC0415
    from rfm_core.io.sync import ApproximateTimeSynchronizer  # noqa: PLC0415

    synced = [t for t in (color_topic, info_topic, depth_topic, *extra_topics) if t]
    if len(synced) > 4:
        raise ValueError(f'at most four synchronised topics, got {synced}')
    index = {t: i for i, t in enumerate(synced)}
    wanted = set(synced) | ({imu_topic} if imu_topic else set())
    ready = []
    sync = ApproximateTimeSynchronizer(len(synced), slop_ns, queue_size=30,
                                       callback=lambda *msgs: ready.append(msgs))
    imu_buffer = []
    with AnyReader([Path(path)]) as reader:
        conns = [c for c in reader.connections if c.topic in wanted]
        missing = {color_topic, info_topic} - {c.topic for c in conns}
        if missing:
            raise ValueError(f'{path} has no {sorted(missing)}')
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == imu_topic:
                imu_buffer.append(msg)
                continue
            sync.add(index[conn.topic], stamp_to_ns(msg.header.stamp), msg)
            while ready:
                group = dict(zip(synced, ready.pop(0)))
                yield {'stamp_ns': stamp_to_ns(group[color_topic].header.stamp), 'color': group[color_topic],
                       'info': group[info_topic], 'depth': group.get(depth_topic), 'imu': imu_buffer,
                       **{t: group[t] for t in extra_topics}}
                imu_buffer = []
