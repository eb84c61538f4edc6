"""A PNG file of a small image, written with the standard library (no imaging package on a robot)."""

from __future__ import annotations

import struct
import zlib

import numpy as np


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def gray_alpha_png(gray: np.ndarray, alpha: np.ndarray) -> bytes:
    """An 8-bit grey-and-alpha PNG (colour type 4).

    Parameters
    ----------
    gray, alpha : ndarray of uint8, shape (H, W)
        Brightness and opacity of each pixel; row 0 is the top of the picture.
    """
    h, w = gray.shape
    pixels = np.empty((h, 1 + 2 * w), np.uint8)
    pixels[:, 0] = 0                      # no filter on any row
    pixels[:, 1::2], pixels[:, 2::2] = gray, alpha
    header = struct.pack(">IIBBBBB", w, h, 8, 4, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(pixels.tobytes(), 6))
            + _chunk(b"IEND", b""))
