"""kdrt.Client: the kdrt HTTP API v1 (proto/openapi.yaml) for numpy users."""

from __future__ import annotations

import json
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import _scan, _transport, _wire
from ._errors import Error
from ._transport import FileBody, Transport
from .png import read_png


class Mesh:
    """A stored mesh as the server reports it: `id` (the SHA-256 of its canonical triangles),
    `triangles`, `vertices`, `bounds` ((2, 3) float64 array: min, max), `tree` (the build
    statistics, a dict, with `build_ms`), `in_memory` (None when not reported) and `summary`,
    the whole JSON object."""

    def __init__(self, summary: dict):
        self.summary = summary
        self.id = summary["id"]
        self.triangles = int(summary["triangles"])
        self.vertices = int(summary["vertices"])
        bounds = summary.get("bounds", {})
        self.bounds = np.array([bounds.get("min", [0, 0, 0]), bounds.get("max", [0, 0, 0])],
                               dtype=np.float64)
        self.tree = dict(summary.get("tree", {}))
        if "build_ms" in summary:
            self.tree["build_ms"] = summary["build_ms"]
        self.in_memory = summary.get("in_memory")

    def __repr__(self):
        return f"kdrt.Mesh(id={self.id[:12]}..., triangles={self.triangles})"

    def __eq__(self, other):
        return isinstance(other, Mesh) and self.summary == other.summary


class Job:
    """An async render job: `id`, `state` ("queued", "running", "done", "failed",
    "cancelled"), `progress` (0 .. 1), `error` (why it failed, else ""), and `status`, the whole
    JSON object."""

    def __init__(self, status: dict):
        self.status = status
        self.id = status["id"]
        self.state = status["state"]
        self.progress = float(status.get("progress", 0.0))
        self.error = status.get("error", "")

    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed", "cancelled")

    def __repr__(self):
        return f"kdrt.Job(id={self.id}, state={self.state}, progress={self.progress:.2f})"


def _mesh_id(mesh) -> str:
    if isinstance(mesh, Mesh):
        return mesh.id
    if isinstance(mesh, str):
        return mesh
    raise Error(kind="input", title="bad mesh", detail=f"expected a kdrt.Mesh or a mesh id "
                f"string; got {type(mesh).__name__}")


def _segment(text: str) -> str:
    """Percent-encodes one path segment: only RFC 3986 unreserved characters stay."""
    out = []
    for byte in text.encode("utf-8"):
        c = chr(byte)
        if c.isascii() and (c.isalnum() or c in "-._~"):
            out.append(c)
        else:
            out.append(f"%{byte:02X}")
    return "".join(out)


def _json_answer(method, path):
    def read(response):
        body = response.read()
        try:
            return json.loads(body)
        except ValueError:
            raise Error(kind="protocol", title="bad response",
                        detail=f"{method} {path}: the answer is not JSON") from None
    return read


def _vec3(value, name):
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 3:
        raise Error(kind="input", title="bad camera", detail=f"camera {name} needs 3 numbers; "
                    f"got {arr.size}")
    return [float(x) for x in arr]


class Client:
    """A client of the kdrt-server at `url` ("http://host:port[/prefix]", "https://...", or
    "host:port"). Connects lazily. Thread-safe: each call takes its own connection(s).

    token:       bearer token for every request (default: the KDRT_TOKEN environment variable).
    timeout:     seconds per socket read or write (a long batch may take longer in total).
    connect_timeout: seconds to set a connection up.
    max_retries: retries after the first attempt, on connection errors and 503 answers.
    chunk_rays:  rays (and distance query points) per request; larger batches are split into
                 chunks of this many...
    connections: ...sent at once on this many keep-alive connections (one thread each).
    poll_interval: seconds between two polls of a job in wait().
    """

    def __init__(self, url="http://127.0.0.1:8080", token=None, timeout=300.0,
                 connect_timeout=5.0, max_retries=4, backoff_initial=0.1, backoff_max=5.0,
                 max_retry_after=60.0, chunk_rays=1 << 16, connections=4, poll_interval=0.1):
        if chunk_rays < 1:
            raise ValueError("chunk_rays must be at least 1")
        if connections < 1:
            raise ValueError("connections must be at least 1")
        if token is None:
            token = os.environ.get("KDRT_TOKEN") or None
        self._t = Transport(url, token, timeout, connect_timeout, max_retries, backoff_initial,
                            backoff_max, max_retry_after, connections)
        self.url = str(self._t.url)
        self.chunk_rays = int(chunk_rays)
        self.connections = int(connections)
        self.poll_interval = poll_interval
        self._pool = None
        self._pool_lock = threading.Lock()
        self._distance_chunk = 0  # points per distance request a 413 taught (0: chunk_rays)

    def close(self):
        """Closes the idle connections and the worker threads (the client stays usable)."""
        with self._pool_lock:
            pool, self._pool = self._pool, None
        if pool:
            pool.shutdown(wait=True)
        self._t.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _json(self, method, path, body=None, headers=None, resend=True, retry_unavailable=True):
        parts = [json.dumps(body).encode()] if body is not None else []
        return self._t.request(method, path, parts, "application/json" if parts else None,
                               headers, _json_answer(method, path), resend, retry_unavailable)

    # ---- Meshes -------------------------------------------------------------------------------

    def upload(self, source, triangles=None, format=None) -> Mesh:
        """Uploads a mesh and returns it as stored (uploading the same triangles again returns
        the stored mesh without a rebuild).

        upload(path[, format]): a mesh file (.obj .ply .off .stl .raw .kdrtmesh, or `format`
        "obj", "ply", "off", "stl", "raw"), streamed from disk in 1 MiB blocks. The server parses it: a bad file
        raises kdrt.Error 422 whose `line` (text formats) or `byte_offset` says where.
        upload(vertices, triangles): arrays of shape (V, 3) (float) and (T, 3) (integer indices),
        sent as the raw format."""
        if triangles is not None:
            parts = _wire.raw_mesh(source, triangles)
            media_type = _wire.RAW_MESH_MEDIA_TYPE
        else:
            path = os.fspath(source)
            if format is not None:
                if format not in _wire.MESH_FORMATS:
                    raise Error(kind="input", title="cannot upload",
                                detail=f"unknown mesh format {format!r} (expected one of "
                                f"{', '.join(_wire.MESH_FORMATS)})")
                media_type = _wire.MESH_FORMATS[format]
            else:
                ext = os.path.splitext(path)[1].lower()
                if ext not in _wire.MESH_MEDIA_TYPES:
                    raise Error(kind="input", title="cannot upload",
                                detail=f'cannot tell the mesh format of "{path}" from its '
                                f"extension (expected .obj, .ply, .off, .stl, .raw or .kdrtmesh)")
                media_type = _wire.MESH_MEDIA_TYPES[ext]
            parts = [FileBody(path)]
        path = self._t.api("/v1/meshes")
        return Mesh(self._t.request("POST", path, parts, media_type, None,
                                    _json_answer("POST", path)))

    def meshes(self) -> list:
        """Every stored mesh, sorted by id."""
        answer = self._json("GET", self._t.api("/v1/meshes"))
        return [Mesh(m) for m in answer["meshes"]]

    def mesh(self, mesh) -> Mesh:
        """One stored mesh (kdrt.Error 404 when unknown)."""
        return Mesh(self._json("GET", self._t.api("/v1/meshes/" + _segment(_mesh_id(mesh)))))

    def remove(self, mesh) -> None:
        """Deletes a stored mesh (kdrt.Error 404 when unknown)."""
        self._t.request("DELETE", self._t.api("/v1/meshes/" + _segment(_mesh_id(mesh))))

    # ---- Rays ---------------------------------------------------------------------------------

    def cast_rays(self, mesh, rays) -> dict:
        """Closest hit of every ray, like Open3D's RaycastingScene.cast_rays.

        rays: float array of shape (..., 6) [ox, oy, oz, dx, dy, dz] (the segment t in [0, inf))
        or (..., 8) [ox, oy, oz, dx, dy, dz, tmin, tmax]; t is in units of the direction's
        length. Returns a dict of arrays shaped like the rays' leading dimensions:
          t_hit          float32 (...),   inf on a miss
          primitive_ids  uint32 (...),    the triangle index, 0xFFFFFFFF (kdrt.NO_HIT) on a miss
          primitive_uvs  float32 (..., 2) barycentric weights of v1 and v2, 0 on a miss
        The three are views of one buffer that the answers were read into (no copies).
        Rays with a NaN or infinite origin or direction component are refused by the server
        (kdrt.Error 400 naming the ray)."""
        records = self._trace(_mesh_id(mesh), rays, occlusion=False)
        lead = records.shape[:-1]
        return {
            "t_hit": records[..., 0],
            "primitive_ids": records.view(np.uint32)[..., 1],
            "primitive_uvs": records[..., 2:4],
        }

    def test_occlusions(self, mesh, rays) -> np.ndarray:
        """Occlusion of every ray (True: some triangle is hit with tmin <= t <= tmax), a bool
        array shaped like the rays' leading dimensions. Rays as for cast_rays."""
        return self._trace(_mesh_id(mesh), rays, occlusion=True)

    def list_intersections(self, mesh, rays, max_hits=16, merge_coincident=False,
                           fields="full", normals=False, points=False) -> dict:
        """Every hit along each ray, like Open3D's RaycastingScene.list_intersections
        (POST /v1/meshes/{id}/intersect_all). Rays as for cast_rays. Each ray keeps its nearest
        `max_hits` hits (1 .. the server's max_hits_per_ray), sorted by t then triangle; with
        `merge_coincident` a ray through a shared edge or vertex counts it once (FORMATS.md).
        Returns a dict of flat arrays over the kept hits, ray by ray:
          ray_splits          uint64 (n + 1,)  hits of ray i are [ray_splits[i], ray_splits[i+1])
          ray_ids             uint32 (hits,)   the ray of each hit (index into the flattened rays)
          t_hit               float32 (hits,)
          primitive_ids       uint32 (hits,)   unless fields="t"
          primitive_uvs       float32 (hits, 2) only with fields="full"
          primitive_normals   float32 (hits, 3) with normals=True: unit right-hand normals
          points              float32 (hits, 3) with points=True: world-space hit points
          counts              uint32 (n,)      all hits of each ray (may exceed those kept)"""
        if fields not in _wire.MULTI_HIT_FIELDS:
            raise _wire.input_error("bad fields", f"fields is {fields!r}, not full, t or t_prim")
        query = (f"max_hits={int(max_hits)}&merge_coincident={str(bool(merge_coincident)).lower()}"
                 f"&fields={fields}&normal={str(bool(normals)).lower()}"
                 f"&point={str(bool(points)).lower()}")
        parts = self._all_hits(_mesh_id(mesh), rays, query,
                               lambda body, n: _wire.decode_multi_hits(body, n))
        offsets, counts, records = [np.zeros(1, dtype=np.uint64)], [], []
        for part in parts:
            offsets.append(part["offsets"][1:] + offsets[-1][-1])
            counts.append(part["counts"])
            records.append(part["records"])
        ray_splits = np.concatenate(offsets).astype(np.uint64)
        rec = np.concatenate(records) if records else np.zeros(
            0, _wire.multi_hit_record_dtype(fields, normals, points))
        out = {
            "ray_splits": ray_splits,
            "ray_ids": np.repeat(np.arange(ray_splits.size - 1, dtype=np.uint32),
                                 np.diff(ray_splits).astype(np.int64)),
            "t_hit": np.ascontiguousarray(rec["t"]),
            "counts": np.concatenate(counts) if counts else np.zeros(0, np.uint32),
        }
        if fields != "t":
            out["primitive_ids"] = np.ascontiguousarray(rec["prim"])
        if fields == "full":
            out["primitive_uvs"] = np.stack([rec["u"], rec["v"]], axis=-1)
        if normals:
            out["primitive_normals"] = np.ascontiguousarray(rec["normal"])
        if points:
            out["points"] = np.ascontiguousarray(rec["point"])
        return out

    def count_intersections(self, mesh, rays, merge_coincident=False) -> np.ndarray:
        """The number of hits of each ray (uint32, shaped like the rays' leading dimensions),
        like Open3D's RaycastingScene.count_intersections. With `merge_coincident` a ray through
        a shared edge or vertex counts it once, so on a closed mesh the count's parity tells
        inside (odd, for a ray starting inside) from outside."""
        arr = _wire.as_rays(rays)
        query = f"count_only=true&merge_coincident={str(bool(merge_coincident)).lower()}"
        parts = self._all_hits(_mesh_id(mesh), arr, query,
                               lambda body, n: _wire.decode_hit_counts(body, n))
        counts = np.concatenate(parts) if parts else np.zeros(0, np.uint32)
        return counts.reshape(arr.shape[:-1])

    def _all_hits(self, mesh_id, rays, query, decode):
        """The intersect_all answers of `rays` in chunks of chunk_rays, one after another."""
        arr = _wire.as_rays(rays)
        flat = arr.reshape(-1, arr.shape[-1])
        n = flat.shape[0]
        path = self._t.api("/v1/meshes/" + _segment(mesh_id) + "/intersect_all") + "?" + query
        parts = []
        first = 0
        while True:
            count = min(self.chunk_rays, n - first)
            records = _wire.kdrr_records(flat[first:first + count])
            header = _wire.batch_header(_wire.RAY_MAGIC, 0, count)
            body = self._t.request("POST", path, [header, _wire.byte_view(records)],
                                   _wire.RAYS_MEDIA_TYPE, None, lambda r: r.read())
            parts.append(decode(body, count))
            first += count
            if first >= n:
                return parts

    def _workers(self):
        with self._pool_lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=self.connections,
                                                thread_name_prefix="kdrt")
            return self._pool

    def _trace(self, mesh_id, rays, occlusion):
        arr = _wire.as_rays(rays)
        lead = arr.shape[:-1]
        flat = arr.reshape(-1, arr.shape[-1])
        n = flat.shape[0]
        path = self._t.api("/v1/meshes/" + _segment(mesh_id) + "/intersect")
        if occlusion:
            out = np.empty(n, dtype=np.uint8)
            magic, record_bytes, flags = _wire.OCCLUSION_MAGIC, 1, _wire.FLAG_OCCLUSION
        else:
            out = np.empty((n, 4), dtype="<f4")
            magic, record_bytes, flags = _wire.HIT_MAGIC, _wire.HIT_RECORD_BYTES, 0
        chunk = self.chunk_rays
        chunks = max(1, -(-n // chunk))

        def send_chunk(k, conn):
            first = k * chunk
            count = min(chunk, n - first)
            records = _wire.kdrr_records(flat[first:first + count])
            header = _wire.batch_header(_wire.RAY_MAGIC, flags, count)
            target = _wire.byte_view(out[first:first + count])
            expected = _wire.HEADER_BYTES + record_bytes * count

            def read(response):
                length = response.getheader("Content-Length")
                if length is None or int(length) != expected:
                    # Not this batch's answer: read what there is and let the decoder say why.
                    body = response.read(max(expected, _wire.HEADER_BYTES))
                    response.close()
                    conn.close()
                    _wire.check_answer_header(body, magic, count)
                    raise Error(kind="protocol", title="bad response",
                                detail=f"POST {path}: answer of {length} bytes, expected "
                                f"{expected} for {count} rays")
                head = response.read(_wire.HEADER_BYTES)
                _wire.check_answer_header(head, magic, count)
                got = 0
                while got < len(target):  # straight into the output array
                    step = response.readinto(target[got:])
                    if not step:
                        raise OSError("the answer ended early")
                    got += step
                return None

            self._t.request("POST", path, [header, _wire.byte_view(records)],
                            _wire.RAYS_MEDIA_TYPE, None, read, conn=conn)

        if chunks == 1 or self.connections == 1:
            conn = self._t.acquire()
            try:
                for k in range(chunks):
                    send_chunk(k, conn)
            finally:
                self._t.release(conn)
        else:
            # Like the C++ client: each worker takes the next chunk on its own connection; the
            # first failure stops the others and the earliest failing chunk's error is raised.
            next_chunk = iter(range(chunks))
            lock = threading.Lock()
            failures = {}

            def worker():
                conn = self._t.acquire()
                try:
                    while not failures:
                        with lock:
                            k = next(next_chunk, None)
                        if k is None:
                            return
                        try:
                            send_chunk(k, conn)
                        except BaseException as exc:  # noqa: B902 - reraised by the caller
                            with lock:
                                failures[k] = exc
                            return
                finally:
                    self._t.release(conn)

            pool = self._workers()
            futures = [pool.submit(worker) for _ in range(min(self.connections, chunks))]
            for f in futures:
                f.result()
            if failures:
                raise failures[min(failures)]
        if occlusion:
            _wire.check_occlusion_records(out)
            return out.view(np.bool_).reshape(lead)
        return out.reshape(lead + (4,))

    # ---- Distance queries (POST /v1/meshes/{id}/distance) -----------------------------------

    def compute_closest_points(self, mesh, query_points, max_distance=np.inf) -> dict:
        """The closest point on the mesh to every query point, like Open3D's
        RaycastingScene.compute_closest_points, with what the wire (KDRD) carries.

        query_points: float array of shape (..., 3). Only triangles at most `max_distance` away
        count (>= 0; default: no limit). Returns a dict of arrays shaped like the points'
        leading dimensions:
          points         float32 (..., 3) the closest point; NaN where nothing was found
          distance       float32 (...)    to the closest point; inf where nothing was found
          primitive_ids  uint32 (...)     the triangle, 0xFFFFFFFF (kdrt.NO_HIT) where none
          primitive_uvs  float32 (..., 2) barycentric weights of v1 and v2 (point = (1-u-v) v0
                                          + u v1 + v v2), 0 where nothing was found
          features       uint8 (...)      where on the triangle: 0 face, 1 edge v0-v1, 2 edge
                                          v1-v2, 3 edge v2-v0, 4..6 vertex v0..v2, 7 none
                                          (names: kdrt.FEATURES)
        A NaN or infinite coordinate raises kdrt.Error (kind "input") naming the point before
        anything is sent."""
        records, _, lead = self._distance(_mesh_id(mesh), query_points, max_distance, False)
        return {
            "points": np.ascontiguousarray(records["point"]).reshape(lead + (3,)),
            "distance": np.ascontiguousarray(records["distance"]).reshape(lead),
            "primitive_ids": np.ascontiguousarray(records["prim"]).reshape(lead),
            "primitive_uvs": np.stack([records["u"], records["v"]], axis=-1).reshape(lead + (2,)),
            "features": np.ascontiguousarray(records["feature"]).reshape(lead),
        }

    def compute_distance(self, mesh, query_points, max_distance=np.inf) -> np.ndarray:
        """The distance from every query point to the mesh (float32, shaped like the points'
        leading dimensions; inf where no triangle is within `max_distance`), like Open3D's
        RaycastingScene.compute_distance."""
        records, _, lead = self._distance(_mesh_id(mesh), query_points, max_distance, False)
        return np.ascontiguousarray(records["distance"]).reshape(lead)

    def compute_signed_distance(self, mesh, query_points, max_distance=np.inf) -> np.ndarray:
        """The signed distance of every query point (float32, shaped like the points' leading
        dimensions): negative inside, positive outside (0 on the surface), like Open3D's
        RaycastingScene.compute_signed_distance. The server decides the side by the
        angle-weighted pseudonormal of the closest feature, exact on a closed, consistently
        oriented mesh (proto/FORMATS.md). Where the sign is undefined the value is NaN, as the
        server reports it: on a mesh that is not closed (every point; see surface()), and where
        no triangle is within `max_distance`."""
        records, _, lead = self._distance(_mesh_id(mesh), query_points, max_distance, True)
        d = records["distance"]
        side = records["side"]
        out = np.where(side == _wire.SIDE_INSIDE, -d,
                       np.where(side == _wire.SIDE_OUTSIDE, d, np.float32(np.nan)))
        return out.astype(np.float32, copy=False).reshape(lead)

    def compute_occupancy(self, mesh, query_points) -> np.ndarray:
        """1.0 for every query point inside the mesh, 0.0 outside (on the surface counts as
        outside), float32 shaped like the points' leading dimensions, like Open3D's
        RaycastingScene.compute_occupancy. Only a closed, consistently oriented mesh has an
        inside: on any other mesh this raises kdrt.Error (kind "input", title "mesh not
        closed", the detail saying how many boundary, non-manifold and misoriented edges it
        has) rather than guessing."""
        mesh_id = _mesh_id(mesh)
        records, surface, lead = self._distance(mesh_id, query_points, np.inf, True,
                                                require_closed=True)
        return (records["side"] == _wire.SIDE_INSIDE).astype(np.float32).reshape(lead)

    def surface(self, mesh) -> str:
        """Whether the mesh has an inside, as the server says (its X-Kdrt-Surface header):
        "closed", or "not closed: B boundary edges, N non-manifold edges, M misoriented
        edges"."""
        _, surface, _ = self._distance(_mesh_id(mesh), np.zeros((0, 3), np.float32), np.inf,
                                       True)
        return surface

    def _distance(self, mesh_id, query_points, max_distance, signed, require_closed=False):
        """The KDRD records (one structured array, in point order), the X-Kdrt-Surface header
        and the points' leading shape. Points go chunk_rays at a time, one request after
        another; a chunk refused as too large (413: over the server's max_distance_points or
        batch_memory_budget) is sent again in smaller chunks (what its `limit` allows, else
        half), and later calls start from that size. With `require_closed`, a mesh that is not
        closed raises after the first answer."""
        arr = _wire.as_points(query_points)
        lead = arr.shape[:-1]
        flat = arr.reshape(-1, 3)
        n = flat.shape[0]
        max_distance = float(max_distance)
        query = f"signed={'true' if signed else 'false'}"
        if not np.isinf(max_distance) or max_distance < 0:
            query += f"&max_distance={max_distance!r}"
        path = (self._t.api("/v1/meshes/" + _segment(mesh_id) + "/distance") + "?" + query)
        parts, surface, first = [], None, 0
        while True:
            chunk = min(self.chunk_rays, self._distance_chunk or self.chunk_rays)
            count = min(chunk, n - first)
            header = _wire.batch_header(_wire.POINT_MAGIC, 0, count)
            body = _wire.byte_view(_wire.kdrp_records(flat[first:first + count]))
            try:
                _, headers, answer = self._t.request("POST", path, [header, body],
                                                     _wire.POINTS_MEDIA_TYPE)
            except Error as err:
                if err.kind == "server" and err.status == 413 and count > 1:
                    smaller = self._smaller_chunk(err, count)
                    with self._pool_lock:
                        if not self._distance_chunk or smaller < self._distance_chunk:
                            self._distance_chunk = smaller
                    continue
                raise
            parts.append(_wire.decode_distances(answer, count, signed))
            got = headers.get("X-Kdrt-Surface", "")
            if surface is None:
                surface = got
                if require_closed and surface != "closed":
                    raise Error(kind="input", title="mesh not closed",
                                detail=f"mesh {mesh_id} has no inside, so no occupancy: it is "
                                f"{surface or 'of unknown closedness'} (only a closed, "
                                f"consistently oriented mesh has one)")
            elif got != surface:
                raise Error(kind="protocol", title="bad response",
                            detail=f"POST {path}: X-Kdrt-Surface changed between chunks: "
                            f"{surface!r}, then {got!r}")
            first += count
            if first >= n:
                break
        records = np.concatenate(parts) if len(parts) > 1 else parts[0]
        return records, surface, lead

    @staticmethod
    def _smaller_chunk(err, count):
        """After a 413 for `count` points: the points to send at once from now on (< count)."""
        allowed = 0
        if err.limit:
            if err.code == "too_many_rays":
                allowed = int(err.limit)
            elif err.limit >= _wire.HEADER_BYTES + _wire.POINT_RECORD_BYTES:
                allowed = (int(err.limit) - _wire.HEADER_BYTES) // _wire.POINT_RECORD_BYTES
        if allowed <= 0 or allowed >= count:
            allowed = count // 2
        return allowed

    # ---- Renders ------------------------------------------------------------------------------

    @staticmethod
    def _render_request(mesh, width, height, shading, camera, spp, seed, format, compression,
                        tile):
        request = {"mesh": _mesh_id(mesh), "width": int(width), "height": int(height),
                   "shading": shading, "spp": int(spp), "seed": int(seed), "format": format}
        if compression is not None:
            request["compression"] = int(compression)
        if camera is not None:
            cam = dict(camera)
            for key in ("eye", "look_at", "up"):
                if key in cam:
                    cam[key] = _vec3(cam[key], key)
            for key in ("fov", "ortho_height"):
                if key in cam:
                    cam[key] = float(cam[key])  # numpy scalars too
            request["camera"] = cam
        if tile is not None:
            x, y, w, h = tile
            request["tile"] = {"x": int(x), "y": int(y), "w": int(w), "h": int(h)}
        return request

    @staticmethod
    def _image(data: bytes, output: str):
        if output == "bytes":
            return data
        image = read_png(data)
        return image if output == "uint8" else image.astype(np.float32) / np.float32(255)

    @staticmethod
    def _check_output(output, format):
        if output not in ("uint8", "float", "bytes"):
            raise Error(kind="input", title="bad output", detail=f"output {output!r}: expected "
                        f'"uint8", "float" or "bytes"')
        if output != "bytes" and format != "png":
            raise Error(kind="input", title="bad output", detail=f"a {format} image can only be "
                        f'returned as output="bytes" (arrays are decoded from PNG)')

    def render(self, mesh, width=512, height=512, shading="eyelight", camera=None, spp=1, seed=1,
               format="png", output="uint8", compression=None, tile=None):
        """Renders synchronously. shading: "normals", "eyelight", "ao", "diffuse", "depth",
        "primid", "geomid"; camera: a dict {"eye", "look_at", "up", "fov", "projection", "ortho_height"}
        (None: a default view framing the mesh); tile (x, y, w, h): a part of the frame.
        output "uint8": an (H, W, C) uint8 array (C = 3, or 4 with alpha), "float": the same as
        float32 in [0, 1] (the PNG's levels / 255: sRGB-encoded for eyelight and diffuse, the
        values themselves for ao, normals, depth, primid and geomid), "bytes": the encoded image (format
        "png", "jpeg"/"jpg" or "exr"; EXR holds the linear values)."""
        self._check_output(output, format)
        request = self._render_request(mesh, width, height, shading, camera, spp, seed, format,
                                       compression, tile)
        path = self._t.api("/v1/render")
        _, _, data = self._t.request("POST", path, [json.dumps(request).encode()],
                                     "application/json")
        return self._image(data, output)

    def submit(self, mesh, width=512, height=512, shading="eyelight", camera=None, spp=1,
               seed=1, format="png", compression=None, tile=None) -> Job:
        """Queues the render as an async job (arguments as for render) and returns it. Not
        resent after a lost connection once the request may have been sent (it could queue a
        second job); resent on 503."""
        request = self._render_request(mesh, width, height, shading, camera, spp, seed, format,
                                       compression, tile)
        path = self._t.api("/v1/render")

        def read(response):
            body = response.read()
            if response.status != 202:
                raise Error(kind="protocol", title="bad response", status=response.status,
                            detail=f"POST {path}: status {response.status} instead of 202 (the "
                            f"server did not queue a job)")
            return json.loads(body)

        return Job(self._t.request("POST", path, [json.dumps(request).encode()],
                                   "application/json", {"Prefer": "respond-async"}, read,
                                   resend=False))

    def job(self, job) -> Job:
        """The job's current status."""
        job_id = job.id if isinstance(job, Job) else job
        return Job(self._json("GET", self._t.api("/v1/jobs/" + _segment(job_id))))

    def wait(self, job, progress=None, output="uint8"):
        """Polls the job every poll_interval seconds until it finishes, calling progress(job)
        after every poll (returning False cancels the job and raises kdrt.Error "cancelled"),
        then returns its image (output as for render). A failed job raises kdrt.Error
        "job_failed", a cancelled one "cancelled"."""
        job_id = job.id if isinstance(job, Job) else job
        fmt = job.status.get("format", "png") if isinstance(job, Job) else "png"
        self._check_output(output, "png" if fmt == "png" else fmt)
        while True:
            status = self.job(job_id)
            if progress is not None and progress(status) is False:
                try:
                    self.cancel(status)
                except Error:
                    pass
                raise Error(kind="cancelled", title="cancelled",
                            detail=f"job {job_id} cancelled while waiting for it")
            if status.state == "done":
                return self.result(status, output)
            if status.state == "failed":
                raise Error(kind="job_failed", title="render failed",
                            detail=f"job {job_id}: {status.error}")
            if status.state == "cancelled":
                raise Error(kind="cancelled", title="cancelled",
                            detail=f"job {job_id} was cancelled")
            time.sleep(self.poll_interval)

    def result(self, job, output="uint8"):
        """The image of a finished job (kdrt.Error 409 while it is not done)."""
        job_id = job.id if isinstance(job, Job) else job
        _, _, data = self._t.request("GET", self._t.api(f"/v1/jobs/{_segment(job_id)}/result"))
        return self._image(data, output)

    def cancel(self, job) -> None:
        """Cancels a queued or running job, or forgets a finished one."""
        job_id = job.id if isinstance(job, Job) else job
        self._t.request("DELETE", self._t.api("/v1/jobs/" + _segment(job_id)))

    # ---- Sensor scans (POST /v1/meshes/{id}/scan) ---------------------------------------------

    def _scan(self, mesh, request, pooled=False):
        """The scan's answer body: bytes, or with `pooled` a memoryview of one of the client's
        reused answer buffers (_transport.BodyBuffers), for answers whose decoded arrays are
        views of it (a fresh buffer of a scan's size costs a page fault every 4 KiB)."""
        mesh_id = _mesh_id(mesh)
        path = self._t.api("/v1/meshes/" + _segment(mesh_id) + "/scan?route=" + _segment(mesh_id))
        read = _transport.read_pooled(self._t.bodies) if pooled else None
        _, _, data = self._t.request("POST", path, [json.dumps(request).encode()],
                                     "application/json", read=read)
        return data

    def scan_pinhole(self, mesh, intrinsics=None, pose=None, camera=None, width=None,
                     height=None, output="depth", normals=False, min_range=None,
                     max_range=None) -> dict:
        """A depth camera scan, its rays made on the server. Give intrinsics (fx, fy, cx, cy,
        width, height; a dict or a sequence) and pose (4 x 4 camera-to-world, OpenCV frame: +x
        right, +y down, +z forward), or camera (the renderer's look-at camera: a dict with
        "eye", "look_at", optional "up" and "fov") with width and height. Pixel (i, j) looks
        through (i + 0.5, j + 0.5). Returns {"depth" (or "range" with output="range"): (H, W)
        float32, inf on a miss; "prim": (H, W) uint32, NO_HIT on a miss; with normals=True
        "normals": (H, W, 3) float32 unit geometric normals (the triangle's winding), 0 on a
        miss}. Only hits min_range <= range <= max_range count."""
        request = {"pinhole": _scan.pinhole_request(intrinsics, pose, camera, width, height,
                                                    output, normals, min_range, max_range),
                   "format": "binary"}
        return _scan.decode_depth_image(self._scan(mesh, request, pooled=True))

    def scan_lidar(self, mesh, azimuth_steps, elevation_deg=None, vertical_fov=None,
                   channels=None, returns=1, pose=None, min_range=None,
                   max_range=None, record="points"):
        """A spinning lidar scan, its rays made on the server: per-channel elevation_deg, or
        vertical_fov (lower, upper) with channels (channel 0 the highest); azimuth_steps
        firings over 360 degrees (sensor frame: +x forward = azimuth 0, +y left, +z up,
        counter-clockwise seen from above); up to `returns` hits per beam, nearest first, a beam
        through a shared edge giving one; pose 4 x 4 sensor-to-world (default identity).
        record="points" (the default) asks for KDRL: a structured array (fields x, y, z, range,
        channel, azimuth_index, return_index, prim) in beam order (azimuth-major); beams without
        a hit have no row. record="ranges" asks for the compact KDRB answer (12 bytes a return
        against 32): a dict-like scan (range, beam, prim as primitive_ids, channel,
        azimuth_index, return_index, and points made on first access on the beams' rays, equal
        to KDRL's to rounding, not bit for bit)."""
        answer_format = _scan.lidar_format(record)
        lidar = _scan.lidar_request(azimuth_steps, elevation_deg, vertical_fov, channels,
                                    returns, pose, min_range, max_range)
        body = self._scan(mesh, {"lidar": lidar, "format": answer_format}, pooled=True)
        if answer_format == "ranges":
            return _scan.decode_lidar_ranges(body, lidar)
        return _scan.decode_point_cloud(body)

    def scan_bytes(self, mesh, request: dict) -> bytes:
        """The server's answer to a scan request dict as it is sent (request["format"]:
        "binary", "exr" for a pinhole, "ply" for a lidar), e.g. to save an EXR or PLY file."""
        return self._scan(mesh, request)

    # ---- Operations ---------------------------------------------------------------------------

    def health(self) -> None:
        """GET /healthz: returns when the process answers."""
        self._t.request("GET", self._t.api("/healthz"))

    def ready(self) -> None:
        """GET /readyz: returns when the server is ready; a 503 raises (not retried)."""
        self._t.request("GET", self._t.api("/readyz"), retry_unavailable=False)

    def metrics(self) -> str:
        """GET /metrics: the Prometheus text exposition."""
        _, _, data = self._t.request("GET", self._t.api("/metrics"))
        return data.decode("utf-8")
