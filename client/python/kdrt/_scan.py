"""Sensor scans (POST /v1/meshes/{id}/scan; proto/FORMATS.md, "Sensor scans") on numpy arrays:
the JSON request, and the KDRZ depth image and KDRL point cloud answers decoded with whole-array
numpy operations and the same strict checks as the C++ decoders."""

from __future__ import annotations

import math

import numpy as np

from ._errors import Error
from ._wire import NO_HIT, input_error

#: One KDRL record (kdrt::LidarPoint), little-endian: what Client.scan_lidar returns.
LIDAR_POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("range", "<f4"),
                              ("channel", "<u4"), ("azimuth_index", "<u4"),
                              ("return_index", "<u4"), ("prim", "<u4")])
assert LIDAR_POINT_DTYPE.itemsize == 32


def _bad(detail: str) -> Error:
    return Error(kind="protocol", title="bad response", detail=detail)


def pose_rows(pose, name="pose") -> list:
    """A 4 x 4 array-like as 4 lists of 4 floats (the server checks that it is rigid)."""
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (4, 4):
        raise input_error(f"bad {name}", f"{name} must be a 4 x 4 array (row-major "
                          f"sensor-to-world), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise input_error(f"bad {name}", f"{name} has a NaN or infinite entry")
    return [[float(v) for v in row] for row in arr]


def _range_window(out: dict, min_range, max_range) -> None:
    if min_range is not None:
        out["min_range"] = float(min_range)
    if max_range is not None and math.isfinite(max_range):
        out["max_range"] = float(max_range)


def pinhole_request(intrinsics, pose, camera, width, height, output, normals, min_range,
                    max_range) -> dict:
    """The "pinhole" object of a scan request."""
    p: dict = {}
    if camera is not None:
        if intrinsics is not None or pose is not None:
            raise input_error("bad pinhole", "give either camera (with width and height) or "
                              "intrinsics and pose, not both")
        if width is None or height is None:
            raise input_error("bad pinhole", "a look-at camera needs width and height")
        p["camera"] = {k: [float(x) for x in v] if k != "fov" else float(v)
                       for k, v in camera.items()}
        p["width"], p["height"] = int(width), int(height)
    else:
        if intrinsics is None or pose is None:
            raise input_error("bad pinhole", "a pinhole needs intrinsics (fx, fy, cx, cy, width, "
                              "height) and pose, or camera with width and height")
        k = dict(intrinsics) if isinstance(intrinsics, dict) else dict(
            zip(("fx", "fy", "cx", "cy", "width", "height"), intrinsics))
        missing = [n for n in ("fx", "fy", "cx", "cy", "width", "height") if n not in k]
        if missing:
            raise input_error("bad intrinsics", f"intrinsics lacks {', '.join(missing)}")
        p["intrinsics"] = {n: float(k[n]) for n in ("fx", "fy", "cx", "cy")}
        p["intrinsics"]["width"] = int(k["width"])
        p["intrinsics"]["height"] = int(k["height"])
        p["pose"] = pose_rows(pose)
    if output not in ("depth", "range"):
        raise input_error("bad output", f'output must be "depth" or "range", not {output!r}')
    p["output"] = output
    p["normals"] = bool(normals)
    _range_window(p, min_range, max_range)
    return p


def lidar_request(azimuth_steps, elevation_deg, vertical_fov, channels, returns, pose, min_range,
                  max_range) -> dict:
    """The "lidar" object of a scan request."""
    p: dict = {}
    if elevation_deg is not None:
        if vertical_fov is not None or channels is not None:
            raise input_error("bad lidar", "give either elevation_deg or vertical_fov with "
                              "channels, not both")
        p["elevation_deg"] = [float(e) for e in np.asarray(elevation_deg, dtype=np.float64)
                              .reshape(-1)]
    else:
        if vertical_fov is None or channels is None:
            raise input_error("bad lidar", "a lidar needs elevation_deg, or vertical_fov "
                              "(lower, upper) with channels")
        lo, hi = vertical_fov
        p["vertical_fov"] = [float(lo), float(hi)]
        p["channels"] = int(channels)
    p["azimuth_steps"] = int(azimuth_steps)
    p["returns"] = int(returns)
    if pose is not None:
        p["pose"] = pose_rows(pose)
    _range_window(p, min_range, max_range)
    return p


def decode_depth_image(body: bytes) -> dict:
    """A KDRZ body as {"depth" or "range": (H, W) float32, "prim": (H, W) uint32, and with
    normals "normals": (H, W, 3) float32}; a miss is inf / NO_HIT / 0 0 0."""
    if len(body) < 16:
        raise _bad(f"KDRZ answer has {len(body)} bytes, fewer than its 16-byte header")
    if body[:4] != b"KDRZ":
        raise _bad(f"bad magic {body[:4]!r}, expected b'KDRZ'")
    version, flags, width, height = np.frombuffer(body, dtype="<u2", count=2, offset=4).tolist() \
        + np.frombuffer(body, dtype="<u4", count=2, offset=8).tolist()
    if version != 1 or flags & ~3:
        raise _bad(f"KDRZ version {version} flags {flags:#x} (expected version 1, flags 0..3)")
    if width < 1 or height < 1:
        raise _bad(f"KDRZ image is {width} x {height} pixels")
    n = width * height
    normals = bool(flags & 2)
    want = 16 + n * (20 if normals else 8)
    if len(body) != want:
        raise _bad(f"KDRZ header says {width} x {height} pixels ({want} bytes) but the answer "
                   f"has {len(body)} bytes")
    depth = np.frombuffer(body, dtype="<f4", count=n, offset=16).reshape(height, width)
    prim = np.frombuffer(body, dtype="<u4", count=n, offset=16 + 4 * n).reshape(height, width)
    miss = prim == NO_HIT
    bad = (miss & (depth != np.inf)) | (~miss & ~(np.isfinite(depth) & (depth >= 0)))
    out = {"range" if flags & 1 else "depth": depth, "prim": prim}
    if normals:
        nrm = np.frombuffer(body, dtype="<f4", count=3 * n, offset=16 + 8 * n).reshape(
            height, width, 3)
        bad |= (miss & np.any(nrm != 0, axis=2)) | (~miss & ~np.all(np.isfinite(nrm), axis=2))
        out["normals"] = nrm
    if bad.any():
        j, i = np.argwhere(bad)[0]
        raise _bad(f"KDRZ pixel ({i}, {j}) is inconsistent (a miss must be inf with normal 0, "
                   "a hit finite >= 0)")
    return out


def decode_point_cloud(body: bytes) -> np.ndarray:
    """A KDRL body as a structured array of LIDAR_POINT_DTYPE, in beam order (azimuth-major)."""
    if len(body) < 32:
        raise _bad(f"KDRL answer has {len(body)} bytes, fewer than its 32-byte header")
    if body[:4] != b"KDRL":
        raise _bad(f"bad magic {body[:4]!r}, expected b'KDRL'")
    version, flags = np.frombuffer(body, dtype="<u2", count=2, offset=4).tolist()
    count, channels, steps, returns = np.frombuffer(body, dtype="<u4", count=4,
                                                    offset=8).tolist()
    reserved = int(np.frombuffer(body, dtype="<u8", count=1, offset=24)[0])
    if version != 1 or flags != 0 or reserved != 0:
        raise _bad(f"KDRL version {version} flags {flags:#x} reserved {reserved}")
    if min(channels, steps, returns) < 1:
        raise _bad(f"KDRL channels {channels}, azimuth_steps {steps}, returns {returns}")
    if len(body) != 32 + 32 * count:
        raise _bad(f"KDRL header says {count} points but the answer has {len(body)} bytes")
    points = np.frombuffer(body, dtype=LIDAR_POINT_DTYPE, count=count, offset=32)
    beam = points["azimuth_index"].astype(np.uint64) * channels + points["channel"]
    ok = (np.isfinite(points["x"]) & np.isfinite(points["y"]) & np.isfinite(points["z"])
          & np.isfinite(points["range"]) & (points["range"] >= 0)
          & (points["channel"] < channels) & (points["azimuth_index"] < steps)
          & (points["return_index"] < returns) & (points["prim"] != NO_HIT))
    if count > 1:
        same = beam[1:] == beam[:-1]
        order = np.ones(count, dtype=bool)
        order[1:] = np.where(same, points["return_index"][1:] == points["return_index"][:-1] + 1,
                             (beam[1:] > beam[:-1]) & (points["return_index"][1:] == 0))
        ok &= order
    if count > 0 and points["return_index"][0] != 0:
        ok[0] = False
    if not ok.all():
        raise _bad(f"KDRL point {int(np.flatnonzero(~ok)[0])} is out of range or out of order")
    return points
