"""Sensor scans (POST /v1/meshes/{id}/scan; proto/FORMATS.md, "Sensor scans") on numpy arrays:
the JSON request, and the KDRZ depth image, KDRL point cloud and KDRB lidar ranges answers decoded
with whole-array numpy operations (KDRZ and KDRL with the same strict checks as the C++
decoders)."""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping

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


def lidar_format(record: str) -> str:
    """The scan request's "format" for a lidar answer of `record`: "points" asks for KDRL
    ("binary"), "ranges" for the compact KDRB ("ranges"); anything else is an input error."""
    formats = {"points": "binary", "ranges": "ranges"}
    if record not in formats:
        raise input_error("bad record", f'record must be "ranges" or "points", not {record!r}')
    return formats[record]


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
        raise _bad(f"bad magic {bytes(body[:4])!r}, expected b'KDRZ'")
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
        raise _bad(f"bad magic {bytes(body[:4])!r}, expected b'KDRL'")
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


# ---- KDRB: the compact lidar record (proto/FORMATS.md, "KDRB") ----------------------------------

#: One KDRB record: the return's range, its beam (azimuth_index x channels + channel), its prim.
LIDAR_RANGE_DTYPE = np.dtype([("range", "<f4"), ("beam", "<u4"), ("prim", "<u4")])
assert LIDAR_RANGE_DTYPE.itemsize == 12

_DEG_TO_RAD = math.pi / 180.0
_directions_cache: dict = {}


def lidar_elevations(lidar: dict) -> list:
    """The channels' elevations (degrees) of a request's "lidar" object, as the engine makes
    them from vertical_fov and channels (kdrt::lidar_elevations)."""
    if "elevation_deg" in lidar:
        return [float(e) for e in lidar["elevation_deg"]]
    lo, hi = (float(v) for v in lidar["vertical_fov"])
    n = int(lidar["channels"])
    if n == 1:
        return [0.5 * (lo + hi)]
    return [hi - (hi - lo) * float(c) / float(n - 1) for c in range(n)]


def lidar_directions(elevation_deg, azimuth_steps: int, pose) -> tuple:
    """(origin float32 (3,), directions (3, beams)) of a lidar's beams in beam order
    (azimuth-major), with the engine's arithmetic (kdrt::lidar_ray: double sines and cosines,
    R v / |v| in double, rounded to float32 once), held as float64 planes (x, y, z), which
    numpy gathers fastest. The last two are cached (a sensor that stays put pays once)."""
    m = np.asarray(pose if pose is not None else np.eye(4), dtype=np.float64).reshape(4, 4)
    key = (tuple(elevation_deg), int(azimuth_steps), m.tobytes())
    hit = _directions_cache.get(key)
    if hit is not None:
        return hit
    ce = np.array([math.cos(e * _DEG_TO_RAD) for e in elevation_deg])
    se = np.array([math.sin(e * _DEG_TO_RAD) for e in elevation_deg])
    angles = [2.0 * math.pi * float(k) / float(azimuth_steps) for k in range(azimuth_steps)]
    ca = np.array([math.cos(a) for a in angles])[:, None]
    sa = np.array([math.sin(a) for a in angles])[:, None]
    v0, v1 = (ce * ca).reshape(-1), (ce * sa).reshape(-1)
    v2 = np.broadcast_to(se, (azimuth_steps, se.size)).reshape(-1)
    length = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    d = np.empty((3, v0.size), dtype=np.float64)
    for r in range(3):
        d[r] = ((m[r, 0] * v0 + m[r, 1] * v1 + m[r, 2] * v2) / length).astype(np.float32)
    out = (m[:3, 3].astype(np.float32), d)
    if len(_directions_cache) >= 2:
        _directions_cache.pop(next(iter(_directions_cache)))
    _directions_cache[key] = out
    return out


class LidarScan(Mapping):
    """A lidar scan's returns from a KDRB answer, read like a dict: "range", "beam",
    "primitive_ids" (and "geometry_ids" for a scene) are views of the answer; "channel",
    "azimuth_index", "return_index" and "points" are made from them on first access. "points"
    (N, 3) float32 is each beam's ray at its range (the ray the server traced, made here from the
    sensor the request described; origin + range x direction in double, rounded once): it agrees
    with KDRL's on-triangle points to rounding, not bit for bit. It is column-major (Fortran
    order: made fastest that way); np.ascontiguousarray gives a row-major copy."""

    _LAZY = ("channel", "azimuth_index", "return_index", "points")

    def __init__(self, records, channels, azimuth_steps, returns, lidar, geometry_ids=None):
        self.channels, self.azimuth_steps, self.returns = channels, azimuth_steps, returns
        self._lidar = lidar
        self._v = {"range": records["range"], "beam": records["beam"],
                   "primitive_ids": records["prim"]}
        if geometry_ids is not None:
            self._v["geometry_ids"] = geometry_ids
        self._keys = list(self._v) + list(self._LAZY)

    def __len__(self):
        return len(self._keys)

    def __iter__(self):
        return iter(self._keys)

    def __getitem__(self, key):
        if key not in self._v:
            if key not in self._LAZY:
                raise KeyError(key)
            self._make(key)
        return self._v[key]

    def _make(self, key):
        beam = self._v["beam"]
        n = beam.size
        if beam.size and int(beam.max()) >= self.channels * self.azimuth_steps:
            raise _bad(f"KDRB beam {int(beam.max())} >= channels x azimuth_steps")
        if key in ("channel", "azimuth_index"):
            a, c = np.divmod(beam, np.uint32(self.channels))
            self._v["channel"], self._v["azimuth_index"] = c, a
        elif key == "return_index":
            if self.returns == 1:
                self._v[key] = np.zeros(n, dtype=np.uint32)
            else:
                idx = np.arange(n, dtype=np.int64)
                first = np.ones(n, dtype=bool)
                first[1:] = beam[1:] != beam[:-1]
                start = np.maximum.accumulate(np.where(first, idx, 0))
                self._v[key] = (idx - start).astype(np.uint32)
        else:
            elevations = lidar_elevations(self._lidar)
            if len(elevations) != self.channels or \
                    int(self._lidar["azimuth_steps"]) != self.azimuth_steps:
                raise _bad(f"KDRB answer of {self.channels} x {self.azimuth_steps} beams does "
                           "not match the sensor asked for")
            origin, directions = lidar_directions(elevations, self.azimuth_steps,
                                                  self._lidar.get("pose"))
            # beam and range are strided views of the 12-byte records: index and scale with
            # contiguous copies, the three coordinates as planes (numpy's fastest gather here),
            # then one float32 rounding into a column-major (N, 3) array.
            t = np.take(directions, beam.astype(np.intp), axis=1)
            t *= self._v["range"].astype(np.float64)
            t += origin.astype(np.float64)[:, None]
            points = t.T.astype(np.float32)
            self._v[key] = points


def decode_lidar_ranges(body, lidar: dict, geometry_ids: bool = False) -> LidarScan:
    """A KDRB body (with geometry_ids: a scene's, flag bit 8 and the geometry-id plane) as a
    LidarScan; `lidar` is the request's "lidar" object (for the points). The header and the
    exact size are checked here, that every beam is one of the sensor's when the derived fields
    are made; the records' order is the server's (the C++ decoder checks it)."""
    if len(body) < 32:
        raise _bad(f"KDRB answer has {len(body)} bytes, fewer than its 32-byte header")
    magic, version, flags, count, channels, steps, returns, reserved = struct.unpack_from(
        "<4sHHIIIIQ", body, 0)
    want_flags = 0x0100 if geometry_ids else 0
    if magic != b"KDRB" or version != 1 or flags != want_flags or reserved != 0:
        raise _bad(f"KDRB answer: magic {magic!r} version {version} flags {flags:#x} reserved "
                   f"{reserved} (expected b'KDRB', 1, {want_flags:#x}, 0)")
    if min(channels, steps, returns) < 1:
        raise _bad(f"KDRB channels {channels}, azimuth_steps {steps}, returns {returns}")
    per = 12 + (4 if geometry_ids else 0)
    if len(body) != 32 + per * count:
        raise _bad(f"KDRB header says {count} points ({32 + per * count} bytes) but the answer "
                   f"has {len(body)} bytes")
    records = np.frombuffer(body, dtype=LIDAR_RANGE_DTYPE, count=count, offset=32)
    geoms = (np.frombuffer(body, dtype="<u4", count=count, offset=32 + 12 * count)
             if geometry_ids else None)
    return LidarScan(records, channels, steps, returns, lidar, geoms)
