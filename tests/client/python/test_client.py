"""kdrt.Client against a real kdrt-server: every call, the array conventions, answers equal to
the C++ client's bytes (the kdrt CLI), a 5M-ray chunked batch, and the error paths."""

import os
import socket
import struct
import time

import numpy as np
import pytest

import kdrt

# A unit quad in the z = 0 plane, two triangles: (0,0,0) (1,0,0) (1,1,0) and (0,0,0) (1,1,0) (0,1,0).
QUAD_VERTICES = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
QUAD_TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


def quad_rays(n, rng):
    """Rays from above the quad straight down onto points strictly inside one triangle (never
    on the diagonal), with their expected t and triangle."""
    x = rng.uniform(0.01, 0.99, n).astype(np.float32)
    y = rng.uniform(0.01, 0.99, n).astype(np.float32)
    keep = np.abs(x - y) > 1e-3
    x, y = x[keep], y[keep]
    height = rng.uniform(0.5, 4.0, x.size).astype(np.float32)
    rays = np.zeros((x.size, 6), dtype=np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2] = x, y, height
    rays[:, 5] = -1.0
    return rays, height, np.where(x > y, 0, 1).astype(np.uint32)


def kdrh_bytes(hits):
    """The KDRH body (proto/FORMATS.md) of a cast_rays answer, to compare with the C++ client."""
    t = hits["t_hit"].reshape(-1)
    records = np.empty((t.size, 4), dtype="<f4")
    records[:, 0] = t
    records.view("<u4")[:, 1] = hits["primitive_ids"].reshape(-1)
    records[:, 2:4] = hits["primitive_uvs"].reshape(-1, 2)
    return struct.pack("<4sHHII", b"KDRH", 1, 0, t.size, 0) + records.tobytes()


def read_kdrr(path):
    """A KDRR file's rays as (n, 8) [ox, oy, oz, dx, dy, dz, tmin, tmax] and its flags."""
    data = open(path, "rb").read()
    magic, version, flags, count, _ = struct.unpack("<4sHHII", data[:16])
    assert (magic, version) == (b"KDRR", 1)
    records = np.frombuffer(data, dtype="<f4", offset=16).reshape(count, 8)
    return records[:, [0, 1, 2, 4, 5, 6, 3, 7]], flags


# ---- Operations and meshes ---------------------------------------------------------------------

def test_health_ready_and_metrics(client):
    client.health()
    client.ready()
    assert "kdrt_" in client.metrics()


def test_upload_from_a_path_and_from_arrays(client, data_dir, tmp_path):
    bunny = client.upload(os.path.join(data_dir, "bunny00.off"))
    assert len(bunny.id) == 64 and bunny.triangles > 0 and bunny.vertices > 0
    assert bunny.bounds.shape == (2, 3) and np.all(bunny.bounds[0] < bunny.bounds[1])
    assert bunny.tree["nodes"] > 0 and "build_ms" in bunny.tree

    quad = client.upload(QUAD_VERTICES, QUAD_TRIANGLES)
    assert (quad.triangles, quad.vertices) == (2, 4)
    np.testing.assert_array_equal(quad.bounds, [[0, 0, 0], [1, 1, 0]])
    # The same triangles as an OBJ file are the same mesh (the id hashes the triangles).
    obj = tmp_path / "quad.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    assert client.upload(obj).id == quad.id
    assert client.upload(str(obj), format="obj").id == quad.id
    # Integer vertex arrays and int64 indices are converted.
    assert client.upload(QUAD_VERTICES.astype(np.int32), QUAD_TRIANGLES.astype(np.int64)).id \
        == quad.id


def test_meshes_mesh_and_remove(client):
    tri = client.upload(np.array([[0, 0, 5], [1, 0, 5], [0, 1, 5]], np.float32),
                        np.array([[0, 1, 2]]))
    ids = [m.id for m in client.meshes()]
    assert tri.id in ids and ids == sorted(ids)
    assert client.mesh(tri.id) == client.mesh(tri)
    client.remove(tri)
    assert tri.id not in [m.id for m in client.meshes()]
    with pytest.raises(kdrt.Error) as e:
        client.remove(tri.id)
    assert e.value.status == 404 and e.value.type == "urn:kdrt:problem:unknown-mesh"


# ---- Rays ----------------------------------------------------------------------------------------

def test_cast_rays_shapes_dtypes_and_values(client):
    quad = client.upload(QUAD_VERTICES, QUAD_TRIANGLES)
    rng = np.random.default_rng(7)
    rays, height, triangle = quad_rays(24 * 3, rng)
    rays = rays[:24]
    grid = rays.reshape(2, 3, 4, 6)
    hits = client.cast_rays(quad, grid)
    assert set(hits) == {"t_hit", "primitive_ids", "primitive_uvs"}
    assert hits["t_hit"].shape == (2, 3, 4) and hits["t_hit"].dtype == np.float32
    assert hits["primitive_ids"].shape == (2, 3, 4) and hits["primitive_ids"].dtype == np.uint32
    assert hits["primitive_uvs"].shape == (2, 3, 4, 2)
    assert hits["primitive_uvs"].dtype == np.float32
    np.testing.assert_allclose(hits["t_hit"].reshape(-1), height[:24], rtol=1e-6)
    np.testing.assert_array_equal(hits["primitive_ids"].reshape(-1), triangle[:24])
    # The hit point from the barycentrics is the ray's target.
    v = QUAD_VERTICES[QUAD_TRIANGLES[hits["primitive_ids"].reshape(-1)]]
    u, w = hits["primitive_uvs"].reshape(-1, 2).T
    point = (1 - u - w)[:, None] * v[:, 0] + u[:, None] * v[:, 1] + w[:, None] * v[:, 2]
    np.testing.assert_allclose(point[:, :2], rays[:, :2], atol=1e-5)

    # Misses: inf, NO_HIT, zero barycentrics. (..., 8): tmax before the quad is a miss too.
    up = rays[:3].copy()
    up[:, 5] = 1.0
    short = np.concatenate([rays[:3], np.zeros((3, 1), np.float32),
                            (height[:3] * 0.5)[:, None]], axis=1)
    for miss in (client.cast_rays(quad, up), client.cast_rays(quad, short)):
        assert np.all(np.isinf(miss["t_hit"]))
        assert np.all(miss["primitive_ids"] == kdrt.NO_HIT)
        assert np.all(miss["primitive_uvs"] == 0)
    # A float64 list of one ray works; an empty batch gives empty arrays.
    one = client.cast_rays(quad, rays[0].astype(np.float64).tolist())
    assert one["t_hit"].shape == () and one["t_hit"] == pytest.approx(height[0], rel=1e-6)
    empty = client.cast_rays(quad, np.zeros((0, 6), np.float32))
    assert empty["t_hit"].shape == (0,) and empty["primitive_uvs"].shape == (0, 2)


def test_cast_rays_bytes_equal_the_cpp_clients(client, server, bunny, cli, data_dir, tmp_path):
    kdrr, kdrh = tmp_path / "rays.kdrr", tmp_path / "hits.kdrh"
    for kind in ("primary", "diffuse"):
        cli("rays", os.path.join(data_dir, "bunny00.off"), "-o", str(kdrr), "--kind", kind,
            "--res", "300")
        cli("--server", server.url, "trace", bunny.id, str(kdrr), "-o", str(kdrh))
        rays, flags = read_kdrr(kdrr)
        assert flags == 0
        # Small chunks on 3 connections: the answers are put back in order.
        chunked = kdrt.Client(server.url, chunk_rays=5000, connections=3)
        for c in (client, chunked):
            assert kdrh_bytes(c.cast_rays(bunny, rays)) == kdrh.read_bytes()


def test_test_occlusions_equal_the_cpp_clients(client, server, bunny, cli, data_dir, tmp_path):
    kdrr, kdro = tmp_path / "shadow.kdrr", tmp_path / "shadow.kdro"
    cli("rays", os.path.join(data_dir, "bunny00.off"), "-o", str(kdrr), "--kind", "shadow",
        "--res", "300")
    cli("--server", server.url, "trace", bunny.id, str(kdrr), "-o", str(kdro))
    rays, flags = read_kdrr(kdrr)
    assert flags == 1
    occluded = kdrt.Client(server.url, chunk_rays=7000, connections=2).test_occlusions(
        bunny, rays.reshape(-1, 1, 8))
    assert occluded.dtype == np.bool_ and occluded.shape == (rays.shape[0], 1)
    expected = kdro.read_bytes()
    assert struct.pack("<4sHHII", b"KDRO", 1, 0, rays.shape[0], 0) + \
        occluded.astype(np.uint8).tobytes() == expected
    assert 0 < occluded.sum() < occluded.size


def test_five_million_rays_in_chunks(server):
    client = kdrt.Client(server.url, chunk_rays=1 << 18, connections=4)
    quad = client.upload(QUAD_VERTICES, QUAD_TRIANGLES)
    rng = np.random.default_rng(11)
    rays, height, triangle = quad_rays(5_100_000, rng)
    rays, height, triangle = rays[:5_000_000], height[:5_000_000], triangle[:5_000_000]
    assert rays.shape[0] == 5_000_000
    hits = client.cast_rays(quad, rays)
    assert hits["t_hit"].shape == (5_000_000,)
    np.testing.assert_allclose(hits["t_hit"], height, rtol=1e-6)
    np.testing.assert_array_equal(hits["primitive_ids"], triangle)
    occluded = client.test_occlusions(quad, rays)
    assert occluded.all()


# ---- Renders ---------------------------------------------------------------------------------------

def test_render_arrays_and_bytes(client, server, bunny, cli, tmp_path):
    camera = {"eye": np.array([0.0, 0.1, 1.5]), "look_at": [0, 0, 0], "fov": np.float32(40)}
    image = client.render(bunny, 64, 48, camera=camera)
    assert image.shape == (48, 64, 3) and image.dtype == np.uint8
    assert image.min() < image.max()
    as_float = client.render(bunny, 64, 48, camera=camera, output="float")
    assert as_float.dtype == np.float32
    np.testing.assert_array_equal(as_float, image.astype(np.float32) / 255)
    png = client.render(bunny, 64, 48, camera=camera, output="bytes")
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    np.testing.assert_array_equal(kdrt.read_png(png), image)
    # The C++ client's image of the same request has the same pixels.
    out = tmp_path / "cli.png"
    cli("--server", server.url, "render", bunny.id, "-o", str(out), "--size", "64x48",
        "--eye", "0,0.1,1.5", "--look-at", "0,0,0", "--fov", "40", "--quiet")
    np.testing.assert_array_equal(kdrt.read_png(out.read_bytes()), image)
    # Every libpng filter choice decodes to the same pixels (level 9: adaptive filters).
    for level in (0, 9):
        np.testing.assert_array_equal(
            client.render(bunny, 64, 48, camera=camera, compression=level), image)
    exr = client.render(bunny, 16, 16, format="exr", output="bytes")
    assert exr[:4] == b"\x76\x2f\x31\x01"  # the OpenEXR magic


def test_async_render_with_progress_and_cancel(client, bunny):
    job = client.submit(bunny, 96, 64, shading="ao", spp=2)
    assert job.state in ("queued", "running", "done") and len(job.id) == 32
    seen = []
    image = client.wait(job, progress=lambda j: seen.append(j.progress))
    assert image.shape == (64, 96, 3)
    assert seen and seen[-1] == 1.0 and seen == sorted(seen)
    assert client.job(job).state == "done"
    np.testing.assert_array_equal(client.result(job), image)
    np.testing.assert_array_equal(client.render(bunny, 96, 64, shading="ao", spp=2), image)

    big = client.submit(bunny, 2048, 2048, shading="ao", spp=64)
    with pytest.raises(kdrt.Error) as e:
        client.wait(big, progress=lambda j: False)
    assert e.value.kind == "cancelled"
    for _ in range(1000):  # the job stops before its next tile
        if client.job(big).state == "cancelled":
            break
        time.sleep(0.01)
    assert client.job(big).state == "cancelled"
    client.cancel(big)  # a finished job is forgotten
    with pytest.raises(kdrt.Error) as e:
        client.job(big)
    assert e.value.status == 404


# ---- Errors --------------------------------------------------------------------------------------

def test_server_down_is_a_connection_error():
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    c = kdrt.Client(f"http://127.0.0.1:{port}", max_retries=2, backoff_initial=0.01)
    with pytest.raises(kdrt.Error) as e:
        c.cast_rays("ab" * 32, np.zeros((10, 6), np.float32))
    err = e.value
    assert err.kind == "connection" and err.title == "cannot connect" and err.status == 0
    assert "Connection refused" in err.detail and err.attempts == 3
    assert f"127.0.0.1:{port}" in str(err)


def test_unknown_mesh_is_a_404_with_the_problem_fields(client):
    with pytest.raises(kdrt.Error) as e:
        client.cast_rays("0" * 64, np.zeros((100_000, 6), np.float32))
    err = e.value
    assert err.kind == "server" and err.status == 404 and err.title == "Unknown mesh"
    assert err.type == "urn:kdrt:problem:unknown-mesh" and "0" * 64 in err.detail
    assert err.problem["status"] == 404 and err.request_id
    assert str(err).startswith("404 Unknown mesh: ")


def test_a_bad_mesh_file_is_a_422_naming_the_line(client, tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n")
    with pytest.raises(kdrt.Error) as e:
        client.upload(bad)
    err = e.value
    assert err.status == 422 and err.line == 3 and err.problem["line"] == 3
    assert err.type == "urn:kdrt:problem:mesh-parse-error"
    raw = tmp_path / "bad.raw"  # binary formats name the byte offset instead
    raw.write_bytes(struct.pack("<II", 3, 1) + b"\0" * 10)
    with pytest.raises(kdrt.Error) as e:
        client.upload(raw)
    assert e.value.status == 422 and e.value.byte_offset is not None


def test_a_nan_ray_is_refused_naming_the_ray(client):
    quad = client.upload(QUAD_VERTICES, QUAD_TRIANGLES)
    rays = np.zeros((10, 6), np.float32)
    rays[:, 5] = -1
    rays[7, 4] = np.nan
    with pytest.raises(kdrt.Error) as e:
        client.cast_rays(quad, rays)
    assert e.value.status == 400 and "ray 7" in e.value.detail and "dy" in e.value.detail


def test_local_input_errors(client, tmp_path):
    (tmp_path / "folder.obj").mkdir()
    cases = [
        lambda: client.cast_rays("ab" * 32, np.zeros((4, 7), np.float32)),
        lambda: client.cast_rays("ab" * 32, np.array(["a"] * 6)),
        lambda: client.upload(tmp_path / "mesh.xyz"),
        lambda: client.upload(tmp_path / "missing.obj"),
        lambda: client.upload(tmp_path / "folder.obj"),
        lambda: client.upload(QUAD_VERTICES, np.array([[0, 1, 4]])),
        lambda: client.upload(QUAD_VERTICES[:, :2], QUAD_TRIANGLES),
        lambda: client.render("ab" * 32, 8, 8, format="exr"),
    ]
    for case in cases:
        with pytest.raises(kdrt.Error) as e:
            case()
        assert e.value.kind == "input" and e.value.detail, e.value
    with pytest.raises(ValueError):
        kdrt.Client("ftp://host")


def test_the_token_is_sent_and_a_wrong_one_is_401():
    from conftest import Server
    s = Server("--token", "s3cret")
    try:
        with pytest.raises(kdrt.Error) as e:
            kdrt.Client(s.url, token="wrong").meshes()
        assert e.value.status == 401
        good = kdrt.Client(s.url, token="s3cret")
        quad = good.upload(QUAD_VERTICES, QUAD_TRIANGLES)
        assert good.cast_rays(quad, quad_rays(10, np.random.default_rng(1))[0])["t_hit"].size
    finally:
        s.stop()


# ---- Every hit along a ray ---------------------------------------------------------------------

# The cube [0, 1]^3, 12 triangles wound outwards with shared vertices.
CUBE_VERTICES = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                          [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float32)
CUBE_TRIANGLES = np.array([[0, 3, 2], [0, 2, 1], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                           [2, 3, 7], [2, 7, 6], [1, 2, 6], [1, 6, 5], [0, 4, 7], [0, 7, 3]],
                          dtype=np.uint32)


def test_list_and_count_intersections(client):
    cube = client.upload(CUBE_VERTICES, CUBE_TRIANGLES)
    rng = np.random.default_rng(3)
    n = 200
    # Straight down through the cube at random points, and through its face diagonals (a shared
    # edge of two triangles), from above.
    rays = np.zeros((n, 6), dtype=np.float32)
    rays[:, 0] = rng.uniform(0.05, 0.95, n)
    rays[:, 1] = rng.uniform(0.05, 0.95, n)
    rays[n // 2:, 1] = rays[n // 2:, 0]  # on the diagonal x = y of the top and bottom faces
    rays[:, 2] = 3.0
    rays[:, 5] = -1.0
    hits = client.list_intersections(cube, rays, max_hits=8, normals=True, points=True)
    assert hits["ray_splits"].shape == (n + 1,) and hits["ray_splits"].dtype == np.uint64
    assert hits["t_hit"].dtype == np.float32 and hits["primitive_ids"].dtype == np.uint32
    kept = np.diff(hits["ray_splits"])
    np.testing.assert_array_equal(kept, hits["counts"])
    assert (kept[: n // 2] == 2).all()   # in at the top, out at the bottom
    assert (kept[n // 2:] == 4).all()    # both triangles of each face on the diagonal
    np.testing.assert_array_equal(hits["ray_ids"], np.repeat(np.arange(n), kept.astype(np.int64)))
    # Sorted by t within each ray; points on the ray; normals unit and outward (z = +-1).
    t = hits["t_hit"]
    same_ray = hits["ray_ids"][1:] == hits["ray_ids"][:-1]
    assert (t[1:][same_ray] >= t[:-1][same_ray]).all()
    np.testing.assert_allclose(np.abs(hits["primitive_normals"][:, 2]), 1.0)
    expect_z = 3.0 - t
    np.testing.assert_allclose(hits["points"][:, 2], expect_z, atol=1e-6)
    top = hits["points"][:, 2] > 0.5
    assert (hits["primitive_normals"][top, 2] > 0).all()
    # Merged, every ray crosses twice; the counts say the same.
    merged = client.list_intersections(cube, rays, max_hits=8, merge_coincident=True,
                                       fields="t_prim")
    assert "primitive_uvs" not in merged
    assert (np.diff(merged["ray_splits"]) == 2).all()
    np.testing.assert_array_equal(client.count_intersections(cube, rays, merge_coincident=True),
                                  np.full(n, 2, np.uint32))
    counts = client.count_intersections(cube, rays.reshape(10, 20, 6))
    assert counts.shape == (10, 20) and counts.dtype == np.uint32
    np.testing.assert_array_equal(counts.reshape(-1), kept)
    # max_hits keeps the nearest: the top face.
    one = client.list_intersections(cube, rays, max_hits=1, fields="t")
    np.testing.assert_allclose(one["t_hit"], 2.0)
    np.testing.assert_array_equal(one["counts"], kept)


def test_list_intersections_chunks_and_equals_the_cli(client, server, cli, tmp_path):
    cube = client.upload(CUBE_VERTICES, CUBE_TRIANGLES)
    rng = np.random.default_rng(5)
    origins = rng.uniform(-1, 2, (500, 3)).astype(np.float32)
    targets = rng.uniform(0, 1, (500, 3)).astype(np.float32)
    rays = np.concatenate([origins, targets - origins, np.zeros((500, 1), np.float32),
                           np.full((500, 1), np.inf, np.float32)], axis=1)
    kdrr = tmp_path / "cube.kdrr"
    records = rays[:, [0, 1, 2, 6, 3, 4, 5, 7]].astype("<f4")
    kdrr.write_bytes(struct.pack("<4sHHII", b"KDRR", 1, 0, 500, 0) + records.tobytes())
    out = tmp_path / "cube.kdrm"
    cli("--server", server.url, "hits", cube.id, str(kdrr), "--all", "-o", str(out),
        "--max-hits", "3", "--merge")
    from kdrt import _wire
    want = _wire.decode_multi_hits(out.read_bytes(), 500)
    for c in (client, kdrt.Client(server.url, chunk_rays=77)):
        got = c.list_intersections(cube, rays, max_hits=3, merge_coincident=True)
        np.testing.assert_array_equal(got["ray_splits"], want["offsets"])
        np.testing.assert_array_equal(got["counts"], want["counts"])
        np.testing.assert_array_equal(got["t_hit"], want["records"]["t"])
        np.testing.assert_array_equal(got["primitive_ids"], want["records"]["prim"])


def test_list_intersections_errors_name_the_parameter(client):
    cube = client.upload(CUBE_VERTICES, CUBE_TRIANGLES)
    rays = np.array([[0.5, 0.5, 3, 0, 0, -1]], dtype=np.float32)
    for kwargs, name in (({"max_hits": 0}, "max_hits"), ({"max_hits": 10**7}, "max_hits")):
        with pytest.raises(kdrt.Error) as info:
            client.list_intersections(cube, rays, **kwargs)
        assert info.value.status == 400 and name in info.value.detail
    with pytest.raises(kdrt.Error) as info:
        client.list_intersections(cube, rays, fields="uv")
    assert info.value.kind == "input"
