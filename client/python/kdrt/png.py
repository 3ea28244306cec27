"""8-bit PNG read and write with numpy and the standard library's zlib only.

write_png(path_or_file, image): image uint8 of shape (H, W) gray, (H, W, 3) RGB or (H, W, 4) RGBA.
read_png(data) -> uint8 array (H, W, C): 8-bit gray, gray+alpha, RGB or RGBA, not interlaced (what
kdrt-server writes; palette, 16-bit and interlaced images are refused with a ValueError). Rows
filtered with None, Sub or Up decode with whole-row numpy operations; Average and Paeth (which
libpng's adaptive filtering may choose at compression levels 4-9) need a loop over the pixels of
each row and are slower.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> PNG colour type
_CHANNELS = {0: 1, 4: 2, 2: 3, 6: 4}     # PNG colour type -> channels


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(image, level: int = 6) -> bytes:
    """The PNG file of an 8-bit image (rows filtered with None: simple and exact)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"write_png needs a uint8 image; got dtype {img.dtype}")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in _COLOR_TYPES or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"write_png needs shape (H, W), (H, W, 3) or (H, W, 4); got {img.shape}")
    height, width, channels = img.shape
    rows = np.zeros((height, 1 + width * channels), dtype=np.uint8)  # filter byte 0 = None
    rows[:, 1:] = img.reshape(height, width * channels)
    header = struct.pack(">IIBBBBB", width, height, 8, _COLOR_TYPES[channels], 0, 0, 0)
    return (SIGNATURE + _chunk(b"IHDR", header) +
            _chunk(b"IDAT", zlib.compress(rows.tobytes(), level)) + _chunk(b"IEND", b""))


def write_png(file, image, level: int = 6) -> None:
    """Writes `image` (see encode_png) to a path or a binary file object."""
    data = encode_png(image, level)
    if hasattr(file, "write"):
        file.write(data)
    else:
        with open(file, "wb") as f:
            f.write(data)


def _paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def read_png(data) -> np.ndarray:
    """Decodes an 8-bit PNG (bytes, or a path) into a uint8 array of shape (H, W, C)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        with open(data, "rb") as f:
            data = f.read()
    data = bytes(data)
    if data[:8] != SIGNATURE:
        raise ValueError("not a PNG file (bad signature)")
    at = 8
    header = None
    idat = []
    while at + 8 <= len(data):
        (length,) = struct.unpack(">I", data[at:at + 4])
        kind = data[at + 4:at + 8]
        body = data[at + 8:at + 8 + length]
        if len(body) != length:
            raise ValueError(f"truncated PNG chunk {kind!r} at byte {at}")
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        at += 12 + length
    if header is None:
        raise ValueError("PNG without an IHDR chunk")
    width, height, depth, color, _, _, interlace = header
    if depth != 8 or color not in _CHANNELS or interlace != 0:
        raise ValueError(f"unsupported PNG: bit depth {depth}, colour type {color}, "
                         f"interlace {interlace} (8-bit gray/RGB/RGBA, not interlaced, only)")
    channels = _CHANNELS[color]
    stride = width * channels
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), dtype=np.uint8)
    if raw.size != height * (stride + 1):
        raise ValueError(f"PNG image data has {raw.size} bytes, expected {height * (stride + 1)}")
    rows = raw.reshape(height, stride + 1)
    filters = rows[:, 0]
    out = np.empty((height, stride), dtype=np.uint8)
    prev = np.zeros(stride, dtype=np.uint8)
    for y in range(height):
        line = rows[y, 1:]
        f = filters[y]
        if f == 0:
            cur = line
        elif f == 1:  # Sub: running sum per channel, modulo 256
            cur = np.cumsum(line.reshape(width, channels), axis=0, dtype=np.uint8).reshape(-1)
        elif f == 2:  # Up
            cur = line + prev
        elif f in (3, 4):  # Average, Paeth: each pixel depends on the one to its left
            cur = np.empty(stride, dtype=np.uint8)
            up = prev.astype(np.int16)
            left = np.zeros(channels, dtype=np.int16)
            up_left = np.zeros(channels, dtype=np.int16)
            src = line.astype(np.int16)
            for x in range(0, stride, channels):
                b = up[x:x + channels]
                if f == 3:
                    pred = (left + b) // 2
                else:
                    pred = _paeth(left, b, up_left)
                value = (src[x:x + channels] + pred) & 0xFF
                cur[x:x + channels] = value
                left, up_left = value, b
        else:
            raise ValueError(f"PNG row {y} has unknown filter type {f}")
        out[y] = cur
        prev = out[y]
    return out.reshape(height, width, channels)
