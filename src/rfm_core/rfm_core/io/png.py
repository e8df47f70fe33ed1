"""Minimal PNG writer (8-bit grey, RGB or RGBA) with zlib only: no imaging dependency."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

__all__ = ['encode_png', 'write_png']


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', zlib.crc32(kind + data))


def encode_png(image) -> bytes:
    """PNG bytes of a uint8 array (H, W), (H, W, 3) or (H, W, 4)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f'PNG writer takes uint8 images, got {img.dtype}')
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 3, 4):
        raise ValueError(f'expected (H, W), (H, W, 3) or (H, W, 4), got {img.shape}')
    h, w, c = img.shape
    color_type = {1: 0, 3: 2, 4: 6}[c]
    raw = np.concatenate([np.zeros((h, 1), np.uint8), img.reshape(h, w * c)], axis=1)
    header = struct.pack('>IIBBBBB', w, h, 8, color_type, 0, 0, 0)
    return (b'\x89PNG\r\n\x1a\n' + _chunk(b'IHDR', header)
            + _chunk(b'IDAT', zlib.compress(raw.tobytes(), 6)) + _chunk(b'IEND', b''))


def write_png(path, image) -> Path:
    """Write ``image`` as a PNG file; returns the path."""
    path = Path(path)
    path.write_bytes(encode_png(image))
    return path
