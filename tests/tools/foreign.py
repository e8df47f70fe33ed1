"""Bags as a user records them elsewhere, made from an rfm sim bag: camera topics only (no
/ground_truth/*), depth stamped a few ms after colour (as real drivers stamp it), colour
optionally JPEG-compressed (image_transport's ``compressed``), and a topic of a type nobody
here subscribes to."""
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

KEEP = ('/camera/', '/imu/', '/tf_static')


def foreign_bag(src, dst, depth_offset_ms: float = 0.0, compressed: bool = False, extra_topic: bool = True) -> Path:
    dst = Path(dst)
    offset = int(depth_offset_ms * 1e6)
    out_msgs = []
    with AnyReader([Path(src)]) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        store = get_typestore(Stores.ROS2_JAZZY)        # the camera topics' types, and String
        conns = [c for c in reader.connections if c.topic.startswith(KEEP)]
        out = {}
        for c in conns:
            topic, msgtype = c.topic, c.msgtype
            if compressed and topic == '/camera/color/image_raw':
                topic, msgtype = topic + '/compressed', 'sensor_msgs/msg/CompressedImage'
            out[c.id] = writer.add_connection(topic, msgtype, typestore=store,
                                              offered_qos_profiles=c.ext.offered_qos_profiles)
        chatter = (writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=store)
                   if extra_topic else None)
        for c, t, raw in reader.messages(connections=conns):
            if c.topic == '/camera/depth/image_raw' and offset:
                msg = reader.deserialize(raw, c.msgtype)
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec + offset
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
                raw, t = store.serialize_cdr(msg, c.msgtype), t + offset
            elif compressed and c.topic == '/camera/color/image_raw':
                raw = _jpeg(reader.deserialize(raw, c.msgtype), store)
            out_msgs.append((t, out[c.id], bytes(raw)))
            if chatter is not None and c.topic == '/camera/color/image_raw':
                text = store.types['std_msgs/msg/String'](data='hello')
                out_msgs.append((t + 1, chatter, store.serialize_cdr(text, 'std_msgs/msg/String')))
        for t, conn, raw in sorted(out_msgs, key=lambda m: m[0]):
            writer.write(conn, t, raw)
    return dst


def _jpeg(image, store):
    import io

    from PIL import Image as PILImage

    from rfm_core.io.images import image_to_rgb
    buf = io.BytesIO()
    PILImage.fromarray(image_to_rgb(image)).save(buf, format='JPEG', quality=95)
    msg = store.types['sensor_msgs/msg/CompressedImage'](
        header=image.header, format='rgb8; jpeg compressed bgr8',
        data=np.frombuffer(buf.getvalue(), np.uint8))
    return store.serialize_cdr(msg, 'sensor_msgs/msg/CompressedImage')
