"""The binary wire formats of proto/FORMATS.md, on numpy arrays.

KDRR (rays out), KDRH and KDRO (answers back) and the raw mesh. Every layout here follows
FORMATS.md exactly (little-endian, the 16-byte batch header, 32-byte ray records in the order of
kdrt::Ray: ox oy oz tmin dx dy dz tmax; 16-byte hit records t prim u v; 1-byte occlusion records).
Records are built and read with whole-array numpy operations, never per ray in Python.
"""

from __future__ import annotations

import struct

import numpy as np

from ._errors import Error

#: The 16-byte header: magic, version (u16), flags (u16), count (u32), reserved (u32).
BATCH_HEADER = struct.Struct("<4sHHII")
HEADER_BYTES = 16
RAY_RECORD_BYTES = 32
HIT_RECORD_BYTES = 16
OCCLUSION_RECORD_BYTES = 1
BATCH_VERSION = 1
FLAG_OCCLUSION = 0x0001
RAY_MAGIC = b"KDRR"
HIT_MAGIC = b"KDRH"
OCCLUSION_MAGIC = b"KDRO"
#: The largest record count a batch header can hold.
MAX_BATCH_RAYS = 0xFFFFFFFF

RAYS_MEDIA_TYPE = "application/x-kdrt-rays"
RAW_MESH_MEDIA_TYPE = "application/x-kdrt-mesh"

#: kdrt::Hit.prim of a miss.
NO_HIT = 0xFFFFFFFF

#: Upload media types by file extension (proto's mesh_media_type).
MESH_MEDIA_TYPES = {
    ".obj": "model/obj",
    ".stl": "model/stl",
    ".ply": "application/ply",
    ".off": "application/x-off",
    ".raw": RAW_MESH_MEDIA_TYPE,
    ".kdrtmesh": RAW_MESH_MEDIA_TYPE,
}
#: The same by format name (Client.upload(path, format=...)).
MESH_FORMATS = {
    "obj": "model/obj",
    "stl": "model/stl",
    "ply": "application/ply",
    "off": "application/x-off",
    "raw": RAW_MESH_MEDIA_TYPE,
}


def input_error(title: str, detail: str) -> Error:
    return Error(kind="input", title=title, detail=detail)


def as_rays(rays) -> np.ndarray:
    """Checks a ray array of shape (..., 6) or (..., 8) and returns it as float32 (no copy when
    it already is float32)."""
    arr = np.asarray(rays)
    if arr.ndim < 1 or arr.shape[-1] not in (6, 8):
        raise input_error(
            "bad rays",
            f"rays must have shape (..., 6) [ox, oy, oz, dx, dy, dz] or (..., 8) "
            f"[ox, oy, oz, dx, dy, dz, tmin, tmax]; got shape {arr.shape}",
        )
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise input_error("bad rays", f"rays must be a float array; got dtype {arr.dtype}")
    count = arr.size // arr.shape[-1]
    if count > MAX_BATCH_RAYS:
        raise input_error(
            "too many rays", f"{count} rays in one call; a batch holds at most {MAX_BATCH_RAYS}"
        )
    return arr.astype(np.float32, copy=False)


def byte_view(arr: np.ndarray) -> memoryview:
    """The bytes of a C-contiguous array as a flat memoryview (no copy; empty arrays work)."""
    return memoryview(arr.reshape(-1).view(np.uint8))


def batch_header(magic: bytes, flags: int, count: int) -> bytes:
    return BATCH_HEADER.pack(magic, BATCH_VERSION, flags, count, 0)


def kdrr_records(rays: np.ndarray) -> np.ndarray:
    """(n, 6|8) float32 rays in [o, d(, tmin, tmax)] order -> (n, 8) float32 KDRR records
    [ox oy oz tmin dx dy dz tmax], little-endian. Six columns mean tmin = 0, tmax = +inf."""
    n = rays.shape[0]
    records = np.empty((n, 8), dtype="<f4")
    records[:, 0:3] = rays[:, 0:3]
    records[:, 4:7] = rays[:, 3:6]
    if rays.shape[1] == 8:
        records[:, 3] = rays[:, 6]
        records[:, 7] = rays[:, 7]
    else:
        records[:, 3] = 0.0
        records[:, 7] = np.inf
    return records


def check_answer_header(header: bytes, magic: bytes, count: int) -> None:
    """Checks a KDRH/KDRO header against FORMATS.md and the request's ray count. Raises a
    "protocol" Error naming the field."""
    if len(header) < HEADER_BYTES:
        raise Error(
            kind="protocol",
            title="bad response",
            detail=f"too_short: body has {len(header)} bytes, less than the 16-byte header",
        )
    got_magic, version, flags, got_count, reserved = BATCH_HEADER.unpack(header[:HEADER_BYTES])
    problem = None
    if got_magic != magic:
        problem = f'bad_magic: bad magic "{got_magic.decode("latin-1")}", expected "{magic.decode()}"'
    elif version != BATCH_VERSION:
        problem = f"bad_version: unsupported version {version}, expected {BATCH_VERSION}"
    elif flags != 0:
        problem = f"bad_flags: flags 0x{flags:04x}, expected 0"
    elif reserved != 0:
        problem = f"bad_reserved: reserved header field is 0x{reserved:08x}, expected 0"
    elif got_count != count:
        problem = f"{got_count} answers for {count} rays"
    if problem:
        raise Error(kind="protocol", title="bad response", detail=problem)


def check_occlusion_records(records: np.ndarray) -> None:
    """KDRO records must be 0 or 1 (FORMATS.md); names the first bad one."""
    bad = np.flatnonzero(records > 1)
    if bad.size:
        i = int(bad[0])
        raise Error(
            kind="protocol",
            title="bad response",
            detail=f"bad_occlusion_value: ray {i}: occlusion value {int(records[i])}, "
            f"expected 0 or 1",
        )


def raw_mesh(vertices, triangles) -> list:
    """The raw mesh body (FORMATS.md): u32 V, u32 T, V x 3 f32, T x 3 u32, as buffers to send."""
    v = np.asarray(vertices)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise input_error("cannot upload", f"vertices must have shape (V, 3); got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise input_error("cannot upload", f"triangles must have shape (T, 3); got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise input_error("cannot upload", f"triangles must be integers; got dtype {t.dtype}")
    if v.shape[0] > 0xFFFFFFFF or t.shape[0] > 0xFFFFFFFF:
        raise input_error("cannot upload", "more than 2^32 - 1 vertices or triangles")
    if t.size and (int(t.min()) < 0 or int(t.max()) >= v.shape[0]):
        bad = int(np.flatnonzero((t.reshape(-1) < 0) | (t.reshape(-1) >= v.shape[0]))[0])
        raise input_error(
            "cannot upload",
            f"triangle {bad // 3} has vertex index {int(t.reshape(-1)[bad])}, "
            f"outside 0 .. {v.shape[0] - 1}",
        )
    verts = np.ascontiguousarray(v, dtype="<f4")
    tris = np.ascontiguousarray(t, dtype="<u4")
    return [struct.pack("<II", v.shape[0], t.shape[0]), byte_view(verts), byte_view(tris)]


# ---- Every hit along a ray: KDRM and KDRC (FORMATS.md, "Every hit along a ray") --------------

#: The 32-byte KDRM header: magic, version, flags, rays, record bytes, hits (u64), max_hits,
#: reserved.
MULTI_HIT_HEADER = struct.Struct("<4sHHIIQII")
MULTI_HIT_MAGIC = b"KDRM"
HIT_COUNT_MAGIC = b"KDRC"
MULTI_HIT_FIELDS = {"full": 0, "t": 1, "t_prim": 2}
MULTI_HIT_FLAG_NORMAL = 0x0004
MULTI_HIT_FLAG_POINT = 0x0008


def _bad(detail: str) -> Error:
    return Error(kind="protocol", title="bad response", detail=detail)


def multi_hit_record_dtype(fields: str, normal: bool, point: bool) -> np.dtype:
    """The numpy dtype of one KDRM record in a layout."""
    parts = [("t", "<f4")]
    if fields != "t":
        parts.append(("prim", "<u4"))
    if fields == "full":
        parts += [("u", "<f4"), ("v", "<f4")]
    if normal:
        parts.append(("normal", "<f4", (3,)))
    if point:
        parts.append(("point", "<f4", (3,)))
    return np.dtype(parts)


def decode_multi_hits(body: bytes, rays: int) -> dict:
    """A KDRM body (for `rays` rays) as arrays: offsets (uint64, rays + 1), counts (uint32),
    records (structured, one per kept hit). Raises a "protocol" Error naming the field."""
    if len(body) < MULTI_HIT_HEADER.size:
        raise _bad(f"too_short: body has {len(body)} bytes, less than the 32-byte KDRM header")
    magic, version, flags, n, record, hits, max_hits, reserved = MULTI_HIT_HEADER.unpack_from(body)
    if magic != MULTI_HIT_MAGIC:
        raise _bad(f'bad_magic: bad magic "{magic.decode("latin-1")}", expected "KDRM"')
    if version != BATCH_VERSION:
        raise _bad(f"bad_version: unsupported version {version}, expected 1")
    fields = {v: k for k, v in MULTI_HIT_FIELDS.items()}.get(flags & 3)
    if flags & ~0x1F or fields is None:
        raise _bad(f"bad_flags: flags 0x{flags:04x}")
    dtype = multi_hit_record_dtype(fields, bool(flags & MULTI_HIT_FLAG_NORMAL),
                                   bool(flags & MULTI_HIT_FLAG_POINT))
    if record != dtype.itemsize or reserved != 0:
        raise _bad(f"bad_flags: record size {record}, expected {dtype.itemsize}")
    if n != rays:
        raise _bad(f"{n} answers for {rays} rays")
    expected = 32 + 8 * (n + 1) + 4 * n + hits * record
    if len(body) != expected:
        raise _bad(f"length_mismatch: {len(body)} bytes, expected {expected}")
    offsets = np.frombuffer(body, dtype="<u8", count=n + 1, offset=32)
    counts = np.frombuffer(body, dtype="<u4", count=n, offset=32 + 8 * (n + 1))
    records = np.frombuffer(body, dtype=dtype, count=hits, offset=32 + 12 * n + 8)
    kept = np.diff(offsets)
    if offsets[0] != 0 or offsets[-1] != hits or (kept.size and (kept > counts).any()):
        raise _bad("bad_offsets: offsets and counts do not describe the records")
    return {"offsets": offsets, "counts": counts, "records": records, "max_hits": max_hits}


def decode_hit_counts(body: bytes, rays: int) -> np.ndarray:
    """A KDRC body as a uint32 array; raises a "protocol" Error naming the field."""
    check_answer_header(body, HIT_COUNT_MAGIC, rays)
    if len(body) != HEADER_BYTES + 4 * rays:
        raise _bad(f"length_mismatch: {len(body)} bytes, expected {HEADER_BYTES + 4 * rays}")
    return np.frombuffer(body, dtype="<u4", count=rays, offset=HEADER_BYTES)


# ---- Distance queries: KDRP and KDRD (FORMATS.md, "Distance queries") -------------------------

POINT_MAGIC = b"KDRP"
DISTANCE_MAGIC = b"KDRD"
POINTS_MEDIA_TYPE = "application/x-kdrt-points"
DISTANCES_MEDIA_TYPE = "application/x-kdrt-distances"
POINT_RECORD_BYTES = 12
#: KDRD flag bit 0: the sides were asked for (signed=true).
DISTANCE_FLAG_SIGNED = 0x0001
#: One KDRD record: f32 distance, u32 prim, f32 u, f32 v, f32 px py pz, u8 feature, u8 side, u16 0.
DISTANCE_RECORD = np.dtype([("distance", "<f4"), ("prim", "<u4"), ("u", "<f4"), ("v", "<f4"),
                            ("point", "<f4", (3,)), ("feature", "u1"), ("side", "u1"),
                            ("reserved", "<u2")])
#: KDRD feature codes: where on its triangle a closest point lies.
FEATURES = ("face", "edge01", "edge12", "edge20", "vertex0", "vertex1", "vertex2", "none")
#: KDRD side codes.
SIDE_OUTSIDE, SIDE_INSIDE, SIDE_UNKNOWN = 0, 1, 2
_AXES = "xyz"


def as_points(points) -> np.ndarray:
    """Checks a point array of shape (..., 3) and returns it as float32 (no copy when it already
    is). A NaN or infinite coordinate is an "input" Error naming the first such point (its index
    in the flattened array) and field, as the server would."""
    arr = np.asarray(points)
    if arr.ndim < 1 or arr.shape[-1] != 3:
        raise input_error("bad query points",
                          f"query points must have shape (..., 3) [x, y, z]; got shape {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise input_error("bad query points", f"query points must be a float array; got dtype "
                          f"{arr.dtype}")
    out = arr.astype(np.float32, copy=False)
    count = out.size // 3
    if count > MAX_BATCH_RAYS:
        raise input_error("too many points", f"{count} query points in one call; a batch holds "
                          f"at most {MAX_BATCH_RAYS}")
    flat = out.reshape(-1, 3)
    bad = ~np.isfinite(flat)
    if bad.any():
        i, axis = (int(k) for k in np.argwhere(bad)[0])
        value = float(flat[i, axis])
        name = "NaN" if np.isnan(value) else ("+inf" if value > 0 else "-inf")
        err = input_error("bad query point", f"point {i}: field {_AXES[axis]} is {name}")
        err.code = "non_finite_point"
        raise err
    return out


def kdrp_records(points: np.ndarray) -> np.ndarray:
    """(n, 3) float32 points -> (n, 3) little-endian KDRP records."""
    return np.ascontiguousarray(points, dtype="<f4")


def decode_distances(body: bytes, count: int, signed: bool) -> np.ndarray:
    """A KDRD body for `count` points as a structured array of DISTANCE_RECORD (a view of the
    body). Checks the header (magic, version, flags: only bit 0, and it must be `signed`, count,
    reserved), the size, and every record's feature (0..7), side (0..2) and reserved bytes,
    naming the first bad point. Raises a "protocol" Error."""
    if len(body) < HEADER_BYTES:
        raise _bad(f"too_short: body has {len(body)} bytes, less than the 16-byte header")
    magic, version, flags, n, reserved = BATCH_HEADER.unpack_from(body)
    if magic != DISTANCE_MAGIC:
        raise _bad(f'bad_magic: bad magic "{magic.decode("latin-1")}", expected "KDRD"')
    if version != BATCH_VERSION:
        raise _bad(f"bad_version: unsupported version {version}, expected {BATCH_VERSION}")
    if flags & ~DISTANCE_FLAG_SIGNED or bool(flags & DISTANCE_FLAG_SIGNED) != bool(signed):
        raise _bad(f"bad_flags: flags 0x{flags:04x} for a {'signed' if signed else 'unsigned'} "
                   f"query")
    if reserved != 0:
        raise _bad(f"bad_reserved: reserved header field is 0x{reserved:08x}, expected 0")
    if n != count:
        raise _bad(f"{n} answers for {count} points")
    expected = HEADER_BYTES + DISTANCE_RECORD.itemsize * n
    if len(body) != expected:
        raise _bad(f"length_mismatch: {len(body)} bytes, expected {expected}")
    records = np.frombuffer(body, dtype=DISTANCE_RECORD, count=n, offset=HEADER_BYTES)
    bad = np.flatnonzero((records["feature"] > 7) | (records["side"] > 2) |
                         (records["reserved"] != 0))
    if bad.size:
        i = int(bad[0])
        r = records[i]
        raise _bad(f"bad_record: point {i}: feature {int(r['feature'])}, side {int(r['side'])}, "
                   f"reserved {int(r['reserved'])}")
    return records
