"""rfm_core.io.images: Image <-> numpy for every supported encoding, padding, byte order."""
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from rfm_core.io.images import (
    ImageFormatError, depth_to_meters, image_to_numpy, image_to_rgb, numpy_to_image,
)

pytest.importorskip('sensor_msgs.msg')

H, W = 5, 7
CASES = {
    'rgb8': lambda rng: rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
    'bgr8': lambda rng: rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
    'mono8': lambda rng: rng.integers(0, 256, (H, W), dtype=np.uint8),
    '16UC1': lambda rng: rng.integers(0, 65536, (H, W), dtype=np.uint16),
    '32FC1': lambda rng: rng.uniform(0.1, 10.0, (H, W)).astype(np.float32),
}


@pytest.mark.parametrize('encoding', sorted(CASES))
@pytest.mark.parametrize('padding', [0, 3, 64])
def test_round_trip_every_encoding_with_padded_step(encoding, padding):
    pixels = CASES[encoding](np.random.default_rng(0))
    packed = W * pixels.itemsize * (3 if pixels.ndim == 3 else 1)
    msg = numpy_to_image(pixels, encoding, step=packed + padding)
    assert msg.step == packed + padding and len(msg.data) == msg.step * H
    out = image_to_numpy(msg)
    assert out.dtype == pixels.dtype and out.shape == pixels.shape
    np.testing.assert_array_equal(out, pixels)


def raw_image(encoding, pixels, step, bigendian):
    """A duck-typed Image built by hand (as a foreign driver would), padding filled with junk."""
    rows = pixels.reshape(H, -1)
    dtype = rows.dtype.newbyteorder('>' if bigendian else '<')
    body = rows.astype(dtype).view(np.uint8).reshape(H, -1)
    pad = np.full((H, step - body.shape[1]), 0xAB, np.uint8)
    return SimpleNamespace(height=H, width=W, encoding=encoding, is_bigendian=bigendian,
                           step=step, data=np.concatenate([body, pad], axis=1).tobytes())


@pytest.mark.parametrize('bigendian', [False, True])
def test_multibyte_encodings_honour_is_bigendian(bigendian):
    rng = np.random.default_rng(1)
    depth_mm = rng.integers(0, 65536, (H, W), dtype=np.uint16)
    out = image_to_numpy(raw_image('16UC1', depth_mm, W * 2 + 6, bigendian))
    np.testing.assert_array_equal(out, depth_mm)
    depth_m = rng.uniform(0, 5, (H, W)).astype(np.float32)
    out = image_to_numpy(raw_image('32FC1', depth_m, W * 4 + 4, bigendian))
    np.testing.assert_array_equal(out, depth_m)
    assert out.dtype.byteorder in ('=', '|', '<' if sys.byteorder == 'little' else '>')


def test_rgb_and_bgr_decode_to_the_same_colours():
    rgb = np.random.default_rng(2).integers(0, 256, (H, W, 3), dtype=np.uint8)
    np.testing.assert_array_equal(image_to_rgb(numpy_to_image(rgb, 'rgb8')), rgb)
    np.testing.assert_array_equal(image_to_rgb(numpy_to_image(rgb[..., ::-1], 'bgr8')), rgb)
    grey = rgb[..., 0]
    np.testing.assert_array_equal(image_to_rgb(numpy_to_image(grey, 'mono8'))[..., 2], grey)


def test_depth_to_meters_units_and_invalid_values():
    mm = np.array([[0, 1000, 65535]], dtype=np.uint16)
    np.testing.assert_allclose(depth_to_meters(numpy_to_image(mm, '16UC1')),
                               [[np.nan, 1.0, 65.535]], rtol=1e-6)
    m = np.array([[np.nan, -1.0, 0.0, np.inf, 2.5]], dtype=np.float32)
    np.testing.assert_array_equal(depth_to_meters(numpy_to_image(m, '32FC1')),
                                  [[np.nan, np.nan, np.nan, np.nan, 2.5]])
    with pytest.raises(ImageFormatError, match='depth'):
        depth_to_meters(numpy_to_image(np.zeros((2, 2, 3), np.uint8), 'rgb8'))


def test_truncated_buffer_is_rejected_with_the_sizes():
    msg = numpy_to_image(np.zeros((H, W, 3), np.uint8), 'rgb8')
    msg.data = msg.data[:-1]
    with pytest.raises(ImageFormatError, match=r'expected step x height = 21 x 5 = 105'):
        image_to_numpy(msg)


def test_inconsistent_headers_are_rejected():
    msg = numpy_to_image(np.zeros((H, W), np.uint16), '16UC1')
    msg.step = W                                          # one byte per pixel: too small
    with pytest.raises(ImageFormatError, match='step'):
        image_to_numpy(msg)
    msg = numpy_to_image(np.zeros((H, W), np.uint8), 'mono8')
    msg.encoding = 'yuv422'
    with pytest.raises(ImageFormatError, match="unsupported image encoding 'yuv422'"):
        image_to_numpy(msg)
    msg.encoding, msg.width = 'mono8', 0
    with pytest.raises(ImageFormatError, match='no pixels'):
        image_to_numpy(msg)
    with pytest.raises(ImageFormatError, match='shape'):
        numpy_to_image(np.zeros((H, W), np.uint8), 'rgb8')
