"""A minimal lossless PNG encoder for camera frames (uint16 or uint8 grayscale), with no imaging dependency.

Camera frames are 16-bit EMCCD counts; PNG keeps them exactly (16-bit grayscale), which a JPEG or an 8-bit
rescale would not, so a frame fetched from the API can be re-analysed.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

__all__ = ["encode_png"]


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(image: np.ndarray) -> bytes:
    """``uint8[h, w]`` or ``uint16[h, w]`` (other integer types are clipped to uint16) as PNG bytes."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"expected a 2D grayscale image, got shape {img.shape}")
    if img.dtype == np.uint8:
        depth, rows = 8, img
    else:
        depth, rows = 16, np.clip(img, 0, 65535).astype(">u2")
    h, w = img.shape
    raw = np.zeros((h, 1 + rows.itemsize * w), dtype=np.uint8)  # filter byte 0 (None) per row
    raw[:, 1:] = rows.view(np.uint8).reshape(h, -1)
    header = struct.pack(">IIBBBBB", w, h, depth, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + _chunk(b"IEND", b"")
    )
