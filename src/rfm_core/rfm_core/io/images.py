"""sensor_msgs/Image <-> numpy, without cv_bridge; sensor_msgs/CompressedImage -> numpy.

Reading works on any object with the fields of sensor_msgs/Image (``height``, ``width``,
``encoding``, ``is_bigendian``, ``step``, ``data``), so it needs no ROS. Writing builds the
message with a factory of :mod:`rfm_core.io.messages` (rclpy by default). Compressed colour
images (image_transport's ``compressed``: JPEG or PNG) are decoded with Pillow; compressed
depth (``compressedDepth``) is not supported.
"""
from __future__ import annotations

import sys

import numpy as np

__all__ = ['ENCODINGS', 'ImageFormatError', 'image_to_numpy', 'numpy_to_image',
           'image_to_rgb', 'compressed_to_rgb', 'depth_to_meters']


class ImageFormatError(ValueError):
    """An Image message that cannot be decoded as described."""


#: encoding -> (numpy scalar type, channels). The scalar's byte order comes from is_bigendian.
ENCODINGS = {
    'rgb8': (np.uint8, 3),
    'bgr8': (np.uint8, 3),
    'rgba8': (np.uint8, 4),
    'bgra8': (np.uint8, 4),
    'mono8': (np.uint8, 1),
    '8UC1': (np.uint8, 1),
    'mono16': (np.uint16, 1),
    '16UC1': (np.uint16, 1),
    '32FC1': (np.float32, 1),
}


def image_to_numpy(msg) -> np.ndarray:
    """Decode an Image message to an array (H, W) or (H, W, C) in native byte order.

    Honours row padding (``step`` larger than a packed row) and ``is_bigendian``. Raises
    :class:`ImageFormatError` with the reason for an unsupported encoding, a ``step`` that
    cannot hold a row, or a buffer shorter than ``step * height``.
    """
    encoding = msg.encoding
    if encoding not in ENCODINGS:
        raise ImageFormatError(
            f"unsupported image encoding '{encoding}'; supported: {', '.join(ENCODINGS)}")
    scalar, channels = ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise ImageFormatError(f'image has no pixels ({width}x{height})')
    dtype = np.dtype(scalar).newbyteorder('>' if msg.is_bigendian else '<')
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ImageFormatError(
            f'step {step} is smaller than one row of {width} x {channels} x {dtype.itemsize} '
            f'bytes = {row_bytes} ({encoding})')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size < step * (height - 1) + row_bytes:
        raise ImageFormatError(
            f'image data has {buf.size} bytes, expected step x height = {step} x {height} = '
            f'{step * height} ({width}x{height} {encoding})')
    rows = np.lib.stride_tricks.as_strided(buf, shape=(height, row_bytes), strides=(step, 1))
    pixels = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder('='), copy=False)
    shape = (height, width) if channels == 1 else (height, width, channels)
    return pixels.reshape(shape)


def compressed_to_rgb(msg) -> np.ndarray:
    """Decode a sensor_msgs/CompressedImage (JPEG or PNG colour or mono, as image_transport's
    ``compressed`` plugin writes them) to RGB uint8 (H, W, 3)."""
    import io  # noqa: PLC0415

    from PIL import Image as PILImage, UnidentifiedImageError  # noqa: PLC0415

    fmt = str(msg.format).lower()
    if 'compresseddepth' in fmt:
        raise ImageFormatError(f"compressed depth ('{msg.format}') is not supported: record or republish "
                               'depth uncompressed (16UC1 or 32FC1)')
    try:
        with PILImage.open(io.BytesIO(bytes(msg.data))) as img:
            rgb = np.asarray(img.convert('RGB'))
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise ImageFormatError(f"cannot decode compressed image (format '{msg.format}'): {exc}") from None
    return np.ascontiguousarray(rgb)


def image_to_rgb(msg) -> np.ndarray:
    """Decode a colour or mono Image (or a CompressedImage) to RGB uint8 (H, W, 3)."""
    if hasattr(msg, 'format') and not hasattr(msg, 'encoding'):
        return compressed_to_rgb(msg)
    pixels = image_to_numpy(msg)
    encoding = msg.encoding
    if encoding in ('rgb8', 'rgba8'):
        return np.ascontiguousarray(pixels[..., :3])
    if encoding in ('bgr8', 'bgra8'):
        return np.ascontiguousarray(pixels[..., 2::-1])
    if encoding in ('mono8', '8UC1'):
        return np.repeat(pixels[..., None], 3, axis=2)
    if encoding == 'mono16':
        return np.repeat((pixels >> 8).astype(np.uint8)[..., None], 3, axis=2)
    raise ImageFormatError(f"'{encoding}' is not a colour encoding")


def depth_to_meters(msg) -> np.ndarray:
    """Decode a depth Image (16UC1 in mm, or 32FC1 in m) to float32 metres (H, W).

    Invalid depth (0 in 16UC1; 0, negative, NaN or inf in 32FC1) becomes NaN.
    """
    pixels = image_to_numpy(msg)
    if msg.encoding in ('16UC1', 'mono16'):
        depth = pixels.astype(np.float32) * np.float32(1e-3)
    elif msg.encoding == '32FC1':
        depth = pixels.astype(np.float32, copy=True)
    else:
        raise ImageFormatError(
            f"'{msg.encoding}' is not a depth encoding; use 16UC1 (mm) or 32FC1 (m)")
    depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
    return depth


def numpy_to_image(pixels, encoding: str, header=None, step: int | None = None, make=None):
    """Encode an array as a sensor_msgs/Image.

    ``pixels`` is (H, W) or (H, W, C) matching ``encoding``. ``step`` may exceed the packed
    row size to produce padded rows (as some drivers do). ``make`` is a message factory of
    :mod:`rfm_core.io.messages` (default: rclpy messages, which needs ROS).
    """
    from rfm_core.io.messages import ROS, header as make_header  # noqa: PLC0415

    make = ROS if make is None else make
    if encoding not in ENCODINGS:
        raise ImageFormatError(f"unsupported image encoding '{encoding}'")
    scalar, channels = ENCODINGS[encoding]
    arr = np.asarray(pixels)
    expected_ndim = 2 if channels == 1 else 3
    if arr.ndim != expected_ndim or (channels > 1 and arr.shape[2] != channels):
        raise ImageFormatError(f'{encoding} needs shape (H, W{"" if channels == 1 else f", {channels}"}), got {arr.shape}')
    arr = np.ascontiguousarray(arr, dtype=scalar)
    height, width = arr.shape[:2]
    row_bytes = width * channels * arr.itemsize
    step = row_bytes if step is None else int(step)
    if step < row_bytes:
        raise ImageFormatError(f'step {step} < row size {row_bytes}')
    rows = arr.reshape(height, -1).view(np.uint8).reshape(height, row_bytes)
    if step > row_bytes:
        rows = np.concatenate([rows, np.zeros((height, step - row_bytes), np.uint8)], axis=1)
    return make('sensor_msgs/msg/Image',
                header=header if header is not None else make_header(make, 0, ''),
                height=height, width=width, encoding=encoding,
                is_bigendian=int(sys.byteorder == 'big'), step=step,
                data=make.uint8_array(rows))
