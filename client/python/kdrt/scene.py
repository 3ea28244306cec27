"""Scenes: many meshes placed by affine transforms and queried as one, shaped like Open3D's
RaycastingScene (add_triangles returns a geometry id; queries answer geometry_ids beside
primitive_ids). The server side is /v1/scenes (proto/FORMATS.md, "Scenes").

    scene = kdrt.Scene(client)
    car = scene.add_triangles(vertices, triangles, transform=T)   # geometry id 0
    shelf = scene.add_triangles(mesh, transform=T2)               # a stored kdrt.Mesh or id
    hits = scene.cast_rays(rays)          # t_hit, geometry_ids, primitive_ids, primitive_uvs
    scene.set_transforms([car], [T3])     # one pose update, one new revision

Instances are sent when the scene is first queried (or commit() is called): a scene of many
instances is one request. Every later add or pose change is one request (a new revision). A
query over the client's chunk_rays is split as the C++ client splits it: the first chunk alone,
then the others in parallel, pinned to the revision the first answered from.
"""

import json
import struct

import numpy as np

from . import _scan, _transport, _wire
from ._errors import Error

SCENE_HIT_FLAG = 0x0100  # flag bit 8: a geometry-id plane ends the answer
POSE_MAGIC = b"KDRX"
POSE_MEDIA_TYPE = "application/x-kdrt-poses"
NO_GEOMETRY = 0xFFFFFFFF
REVISION_HEADER = "X-Kdrt-Scene-Revision"


def _transform(value, name="transform") -> np.ndarray:
    """A 3x4 or 4x4 (last row 0 0 0 1) or 12-number transform as 12 float32, row-major."""
    if value is None:
        return np.array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], dtype="<f4")
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape == (4, 4):
        if not np.array_equal(arr[3], [0, 0, 0, 1]):
            raise Error(kind="input", title="bad transform",
                        detail=f"{name}: the last row of a 4x4 transform must be 0 0 0 1")
        arr = arr[:3]
    if arr.size != 12:
        raise Error(kind="input", title="bad transform",
                    detail=f"{name} needs 12 numbers (3x4) or a 4x4 matrix; got shape {arr.shape}")
    flat = arr.reshape(12)
    if not np.isfinite(flat).all():
        k = int(np.flatnonzero(~np.isfinite(flat))[0])
        raise Error(kind="input", title="bad transform",
                    detail=f"{name}[{k // 4}][{k % 4}] is not finite")
    return flat.astype("<f4")


def split_geometry_ids(body: bytes, records: int):
    """A scene answer -> (mesh body with flag bit 8 cleared, uint32 geometry ids)."""
    if len(body) < 8 + 4 * records:
        raise Error(kind="protocol", title="bad response",
                    detail=f"scene answer of {len(body)} bytes is shorter than its "
                    f"geometry-id plane ({4 * records} bytes)")
    (flags,) = struct.unpack_from("<H", body, 6)
    if not flags & SCENE_HIT_FLAG:
        raise Error(kind="protocol", title="bad response",
                    detail="flag bit 8 (geometry ids) is not set: not a scene answer")
    cut = len(body) - 4 * records
    geometry_ids = np.frombuffer(body, dtype="<u4", count=records, offset=cut)
    mesh = bytearray(body[:cut])
    struct.pack_into("<H", mesh, 6, flags & ~SCENE_HIT_FLAG)
    return bytes(mesh), geometry_ids


_SCENE_POINT_DTYPE = np.dtype([("p", "<f4", (3,)), ("range", "<f4"), ("channel", "<u4"),
                               ("azimuth_index", "<u4"), ("return_index", "<u4"),
                               ("prim", "<u4")])


def decode_scene_point_cloud(body) -> dict:
    """A scene's KDRL answer (flag bit 8, then the geometry-id plane) as Scene.scan_lidar's
    dict. The arrays are views of `body` (no copy: a 64 x 2048 scan is some 3 MB); the header
    and the exact size are checked."""
    if len(body) < 32:
        raise Error(kind="protocol", title="bad response",
                    detail=f"scene KDRL answer has {len(body)} bytes, fewer than its 32-byte "
                    f"header")
    magic, version, flags, n = struct.unpack_from("<4sHHI", body, 0)
    if magic != b"KDRL" or version != 1 or flags != SCENE_HIT_FLAG:
        raise Error(kind="protocol", title="bad response",
                    detail=f"scene KDRL answer: magic {magic!r} version {version} flags "
                    f"{flags:#x} (expected b'KDRL', 1, {SCENE_HIT_FLAG:#x}: the geometry-id "
                    f"plane)")
    if len(body) != 32 + 36 * n:
        raise Error(kind="protocol", title="bad response",
                    detail=f"scene KDRL answer: {n} points make {32 + 36 * n} bytes (32-byte "
                    f"records and the geometry-id plane), but the answer has {len(body)}")
    rec = np.frombuffer(body, dtype=_SCENE_POINT_DTYPE, count=n, offset=32)
    geometry_ids = np.frombuffer(body, dtype="<u4", count=n, offset=32 + 32 * n)
    return {"points": rec["p"], "range": rec["range"], "channel": rec["channel"],
            "azimuth_index": rec["azimuth_index"], "return_index": rec["return_index"],
            "primitive_ids": rec["prim"], "geometry_ids": geometry_ids}


class Scene:
    """A scene on the server of `client` (a kdrt.Client). Thread-compatible (not thread-safe)."""

    def __init__(self, client, scene_id=None):
        self._c = client
        self._t = client._t
        self._pending = []  # instances added locally, not yet sent
        self.id = scene_id
        self.revision = None
        self._count = 0
        if scene_id is not None:
            doc = self.document()
            self._count = len(doc["instances"])

    # ---- Building -------------------------------------------------------------------------

    def add_triangles(self, mesh, triangles=None, transform=None, name=None) -> int:
        """Adds an instance and returns its geometry id. `mesh`: vertices (V, 3) with
        `triangles` (T, 3) (uploaded; the same triangles are stored once), a kdrt.Mesh or a mesh
        id. `transform`: 3x4, 4x4 (last row 0 0 0 1) or 12 numbers, object to world (default
        the identity)."""
        if triangles is not None:
            mesh_id = self._c.upload(mesh, triangles).id
        else:
            mesh_id = getattr(mesh, "id", mesh)
        instance = {"mesh": str(mesh_id), "transform": _transform(transform).tolist()}
        if name is not None:
            instance["name"] = name
        self._pending.append(instance)
        self._count += 1
        return self._count - 1

    def commit(self):
        """Sends the instances added since the last call (creates the scene the first time)."""
        if not self._pending:
            return
        pending, self._pending = self._pending, []
        if self.id is None:
            path = self._t.api("/v1/scenes")
            doc = self._c._json("POST", path, {"instances": pending}, resend=False)
        else:
            path = self._t.api(f"/v1/scenes/{self.id}/instances")
            doc = self._c._json("POST", path, {"add": pending}, resend=False)
        self.id = doc["id"]
        self.revision = doc["revision"]

    def set_transform(self, geometry_id: int, transform) -> int:
        """Moves one instance; returns the new revision."""
        return self.set_transforms([geometry_id], [transform])

    def set_transforms(self, geometry_ids, transforms, if_revision=None) -> int:
        """Moves many instances in one request (KDRX); returns the new revision. With
        `if_revision`, only if the scene is still at that revision (kdrt.Error 412 otherwise)."""
        self.commit()
        ids = np.asarray(geometry_ids, dtype=np.int64).reshape(-1)
        tf = np.asarray(transforms, dtype=np.float64)
        if tf.ndim == 3 and tf.shape[1:] == (4, 4):
            if not np.array_equal(tf[:, 3], np.broadcast_to([0, 0, 0, 1], (tf.shape[0], 4))):
                raise Error(kind="input", title="bad transform",
                            detail="the last row of a 4x4 transform must be 0 0 0 1")
            tf = tf[:, :3]
        tf = tf.reshape(ids.size, 12)
        if not np.isfinite(tf).all():
            i = int(np.flatnonzero(~np.isfinite(tf).all(axis=1))[0])
            raise Error(kind="input", title="bad transform",
                        detail=f"transforms[{i}] has a NaN or infinite entry")
        if ((ids < 0) | (ids >= NO_GEOMETRY)).any():
            raise Error(kind="input", title="bad geometry id",
                        detail="geometry ids are integers 0 .. 2^32 - 2")
        records = np.empty(ids.size, dtype=[("g", "<u4"), ("m", "<f4", (12,))])
        records["g"] = ids
        records["m"] = tf
        header = _wire.batch_header(POSE_MAGIC, 0, ids.size)
        headers = {"If-Match": f'"{if_revision}"'} if if_revision is not None else None
        path = self._t.api(f"/v1/scenes/{self.id}/poses")

        def read(response):
            return json.loads(response.read())

        answer = self._t.request("PATCH", path, [header, _wire.byte_view(records)],
                                 POSE_MEDIA_TYPE, headers, read, False)
        self.revision = answer["revision"]
        return self.revision

    def remove_geometry(self, geometry_id: int) -> None:
        """Removes one instance (the geometry ids after it move down by one)."""
        self.commit()
        path = self._t.api(f"/v1/scenes/{self.id}/instances")
        doc = self._c._json("POST", path, {"remove": [int(geometry_id)]}, resend=False)
        self.revision = doc["revision"]
        self._count = len(doc["instances"])

    def document(self, revision=None) -> dict:
        """The scene as stored (GET /v1/scenes/{id})."""
        self.commit()
        path = self._t.api(f"/v1/scenes/{self.id}")
        if revision is not None:
            path += f"?revision={int(revision)}"
        return self._c._json("GET", path)

    def delete(self) -> None:
        if self.id is not None:
            self._t.request("DELETE", self._t.api(f"/v1/scenes/{self.id}"))
            self.id = None

    # ---- Queries --------------------------------------------------------------------------

    def _post(self, route, parts, media_type, revision=None, pooled=False):
        """One query request; returns (its answer body, the revision it answered from). With
        `pooled` the body is a memoryview of one of the client's reused answer buffers
        (_transport.BodyBuffers), for answers whose decoded arrays are views of it."""
        self.commit()
        path = self._t.api(f"/v1/scenes/{self.id}/{route}")
        if revision is not None:
            path += ("&" if "?" in path else "?") + f"revision={int(revision)}"
        read = _transport.read_pooled(self._t.bodies) if pooled else None
        _, headers, body = self._t.request("POST", path, parts, media_type, read=read)
        answered = headers.get(REVISION_HEADER, "")
        if not answered.isdigit() or (revision is not None and int(answered) != int(revision)):
            raise Error(kind="protocol", title="bad response",
                        detail=f"POST {path}: the answer's {REVISION_HEADER} {answered!r} is not "
                        f"the revision asked for ({revision})")
        return body, int(answered)

    def _chunks(self, route, n, encode, media_type, decode, revision=None):
        """A query of `n` records in chunks of the client's chunk_rays, as the C++ client sends
        it: chunk 0 alone (answered from the current revision, or `revision`), then the others
        at once on up to `connections` connections, each pinned to the revision chunk 0
        answered from, so that every chunk sees the same poses. encode(first, count) gives a
        request body's parts, decode(body, count) an answer's value; returns the values in
        order."""
        chunk = self._c.chunk_rays
        chunks = max(1, -(-n // chunk))

        def send(k, pin):
            first = k * chunk
            count = min(chunk, n - first)
            body, answered = self._post(route, encode(first, count), media_type, pin)
            return decode(body, count), answered

        first, pinned = send(0, revision)
        rest = []
        if chunks > 1:
            if self._c.connections == 1:
                rest = [send(k, pinned) for k in range(1, chunks)]
            else:
                pool = self._c._workers()
                futures = [pool.submit(send, k, pinned) for k in range(1, chunks)]
                rest = [f.result() for f in futures]  # the earliest failing chunk's error
        return [first] + [value for value, _ in rest]

    def _rays(self, rays, occlusion, decode, route="intersect", revision=None):
        """The rays' leading shape, their count and the decoded answers of their chunks."""
        arr = _wire.as_rays(rays)
        flat = arr.reshape(-1, arr.shape[-1])
        flags = _wire.FLAG_OCCLUSION if occlusion else 0

        def encode(first, count):
            records = _wire.kdrr_records(flat[first:first + count])
            return [_wire.batch_header(_wire.RAY_MAGIC, flags, count), _wire.byte_view(records)]

        parts = self._chunks(route, flat.shape[0], encode, _wire.RAYS_MEDIA_TYPE, decode,
                             revision)
        return arr.shape[:-1], flat.shape[0], parts

    def cast_rays(self, rays, revision=None) -> dict:
        """Closest hit of every ray (rays as for Client.cast_rays). Returns arrays shaped like
        the rays' leading dimensions: t_hit, geometry_ids (uint32, NO_GEOMETRY on a miss),
        primitive_ids (the triangle of that instance's mesh), primitive_uvs. A batch over the
        client's chunk_rays goes in chunks, all answered from one revision."""

        def decode(body, count):
            mesh, geometry_ids = split_geometry_ids(body, count)
            _wire.check_answer_header(mesh[:_wire.HEADER_BYTES], _wire.HIT_MAGIC, count)
            records = np.frombuffer(mesh, dtype="<f4", offset=_wire.HEADER_BYTES)
            return records.reshape(count, 4), geometry_ids

        lead, n, parts = self._rays(rays, False, decode, revision=revision)
        records = np.concatenate([r for r, _ in parts]) if len(parts) > 1 else parts[0][0]
        geometry_ids = np.concatenate([g for _, g in parts]) if len(parts) > 1 else parts[0][1]
        return {
            "t_hit": records[:, 0].reshape(lead),
            "geometry_ids": geometry_ids.reshape(lead),
            "primitive_ids": records.view(np.uint32)[:, 1].reshape(lead),
            "primitive_uvs": records[:, 2:4].reshape(lead + (2,)),
        }

    def test_occlusions(self, rays, revision=None) -> np.ndarray:
        def decode(body, count):
            _wire.check_answer_header(body[:_wire.HEADER_BYTES], _wire.OCCLUSION_MAGIC, count)
            out = np.frombuffer(body, dtype=np.uint8, offset=_wire.HEADER_BYTES).copy()
            _wire.check_occlusion_records(out)
            return out

        lead, n, parts = self._rays(rays, True, decode, revision=revision)
        out = np.concatenate(parts) if len(parts) > 1 else parts[0]
        return out.view(np.bool_).reshape(lead)

    def list_intersections(self, rays, max_hits=16, merge_coincident=False,
                           revision=None) -> dict:
        """Every hit along each ray: ray_splits, ray_ids, t_hit, geometry_ids, primitive_ids,
        primitive_uvs over the kept hits (as Client.list_intersections), sorted by t, then
        geometry id, then triangle."""
        route = (f"intersect_all?max_hits={int(max_hits)}"
                 f"&merge_coincident={'true' if merge_coincident else 'false'}")

        def decode(body, count):
            (hits,) = struct.unpack_from("<Q", body, 16)
            mesh, geometry_ids = split_geometry_ids(body, hits)
            return _wire.decode_multi_hits(mesh, count), geometry_ids

        lead, n, parts = self._rays(rays, False, decode, route=route, revision=revision)
        rec = np.concatenate([d["records"] for d, _ in parts])
        geometry_ids = np.concatenate([g for _, g in parts])
        counts = np.concatenate([d["counts"] for d, _ in parts])
        sizes = np.concatenate([np.diff(d["offsets"].astype(np.uint64)) for d, _ in parts])
        splits = np.concatenate([[0], np.cumsum(sizes)]).astype(np.uint64)
        ray_ids = np.repeat(np.arange(n, dtype=np.uint32), sizes.astype(np.int64))
        return {
            "ray_splits": splits,
            "ray_ids": ray_ids,
            "t_hit": rec["t"],
            "geometry_ids": geometry_ids,
            "primitive_ids": rec["prim"],
            "primitive_uvs": np.stack([rec["u"], rec["v"]], axis=-1),
            "counts": counts,
        }

    def compute_closest_points(self, query_points, max_distance=np.inf, revision=None) -> dict:
        """Closest point of the scene to each query point: points, distance, geometry_ids,
        primitive_ids, primitive_uvs (every instance needs a similarity transform)."""
        pts = _wire.as_points(query_points)
        flat = pts.reshape(-1, 3)
        route = "distance"
        if np.isfinite(max_distance):
            route += f"?max_distance={float(max_distance)!r}"

        def encode(first, count):
            records = _wire.kdrp_records(flat[first:first + count])
            return [_wire.batch_header(b"KDRP", 0, count), _wire.byte_view(records)]

        def decode(body, count):
            mesh, geometry_ids = split_geometry_ids(body, count)
            return _wire.decode_distances(mesh, count, False), geometry_ids

        parts = self._chunks(route, flat.shape[0], encode, "application/x-kdrt-points", decode,
                             revision)
        rec = np.concatenate([r for r, _ in parts])
        geometry_ids = np.concatenate([g for _, g in parts])
        lead = pts.shape[:-1]
        return {
            "points": rec["point"].reshape(lead + (3,)),
            "distance": rec["distance"].reshape(lead),
            "geometry_ids": geometry_ids.reshape(lead),
            "primitive_ids": rec["prim"].reshape(lead),
            "primitive_uvs": np.stack([rec["u"], rec["v"]], axis=-1).reshape(lead + (2,)),
        }

    def compute_distance(self, query_points, max_distance=np.inf, revision=None) -> np.ndarray:
        return self.compute_closest_points(query_points, max_distance, revision)["distance"]

    def scan_lidar(self, azimuth_steps, vertical_fov=None, channels=None, elevation_deg=None,
                   pose=None, returns=1, min_range=0.0, max_range=None, revision=None,
                   record="points"):
        """A spinning lidar's returns (as Client.scan_lidar) with each point's geometry id,
        read like a dict: points (N, 3), range, channel, azimuth_index, return_index,
        primitive_ids, geometry_ids. record="points" (the default) asks for KDRL: the server's
        on-triangle points, bit for bit. record="ranges" asks for the compact KDRB answer (12
        bytes a return and the geometry id, against KDRL's 32; for links where the 2.3x fewer
        bytes matter): a _scan.LidarScan whose range, primitive_ids and geometry_ids are views
        of the answer and whose points are made on first access from the beams' rays (equal to
        KDRL's to rounding, not bit for bit)."""
        answer_format = _scan.lidar_format(record)
        lidar = {"azimuth_steps": int(azimuth_steps), "returns": int(returns),
                 "min_range": float(min_range)}
        if elevation_deg is not None:
            lidar["elevation_deg"] = [float(e) for e in elevation_deg]
        else:
            lidar["vertical_fov"] = [float(vertical_fov[0]), float(vertical_fov[1])]
            lidar["channels"] = int(channels)
        if max_range is not None:
            lidar["max_range"] = float(max_range)
        if pose is not None:
            lidar["pose"] = np.asarray(pose, dtype=np.float64).reshape(4, 4).tolist()
        request = {"lidar": lidar, "format": answer_format}
        body, _ = self._post("scan", [json.dumps(request).encode()], "application/json",
                             revision, pooled=True)
        if answer_format == "ranges":
            return _scan.decode_lidar_ranges(body, lidar, geometry_ids=True)
        return decode_scene_point_cloud(body)
