"""kdrt.Scene against a real server: Open3D-shaped answers with geometry ids, a one-instance
identity scene answering exactly as its mesh, batch pose updates as revisions, and refusals
naming the instance and field."""

import json

import numpy as np
import pytest

import kdrt
from conftest import Server


def _box():
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float32)
    t = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int32)
    return v, t


def _box_and_empty_scene(server):
    """A client of `server`, the box uploaded there (its mesh id) and an empty scene."""
    client = kdrt.Client(server.url)
    return client, client.upload(*_box()), kdrt.Scene(client)


def _rays_at(x, n=64, seed=1):
    """Rays along -z through the unit square shifted by x."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.05, 0.95, size=(n, 2)).astype(np.float32)
    rays = np.zeros((n, 6), dtype=np.float32)
    rays[:, 0] = xy[:, 0] + x
    rays[:, 1] = xy[:, 1]
    rays[:, 2] = 5
    rays[:, 5] = -1
    return rays


def test_identity_scene_answers_as_the_mesh(server):
    client, mesh, scene = _box_and_empty_scene(server)
    assert scene.add_triangles(mesh) == 0
    rays = _rays_at(0, 200, seed=3)
    rays[::7, 3:] = [0.3, 0.2, -1]
    got = scene.cast_rays(rays)
    want = client.cast_rays(mesh, rays)
    assert np.array_equal(got["t_hit"], want["t_hit"])
    assert np.array_equal(got["primitive_ids"], want["primitive_ids"])
    assert np.array_equal(got["primitive_uvs"], want["primitive_uvs"])
    hit = np.isfinite(got["t_hit"])
    assert hit.any()
    assert (got["geometry_ids"][hit] == 0).all()
    assert (got["geometry_ids"][~hit] == kdrt.NO_GEOMETRY).all()
    assert np.array_equal(scene.test_occlusions(rays), client.test_occlusions(mesh, rays))


def test_identity_scene_scans_as_the_mesh_and_checks_the_answer(server):
    client, mesh, scene = _box_and_empty_scene(server)
    scene.add_triangles(mesh)
    lidar = dict(azimuth_steps=64, vertical_fov=(-40, 40), channels=16, returns=2,
                 pose=[[1, 0, 0, 0.5], [0, 1, 0, 0.5], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    got = scene.scan_lidar(**lidar, record="points")
    want = client.scan_lidar(mesh, **lidar)
    assert want.shape[0] > 0
    assert np.array_equal(got["points"], np.stack([want["x"], want["y"], want["z"]], axis=-1))
    for key, field in (("range", "range"), ("channel", "channel"),
                       ("azimuth_index", "azimuth_index"), ("return_index", "return_index"),
                       ("primitive_ids", "prim")):
        assert np.array_equal(got[key], want[field]), key
    assert (got["geometry_ids"] == 0).all() and got["geometry_ids"].shape == (want.shape[0],)
    # The answer's header and size are checked: a cut or mesh-form body is a protocol error.
    path = client._t.api(f"/v1/scenes/{scene.id}/scan")
    body = json.dumps({"lidar": {k: v for k, v in lidar.items() if k != "pose"}}).encode()
    _, _, answer = client._t.request("POST", path, [body], "application/json")
    assert kdrt.scene.decode_scene_point_cloud(answer)["geometry_ids"].size > 0
    for bad in (answer[:-4], answer[:20], answer[:6] + b"\0\0" + answer[8:]):
        with pytest.raises(kdrt.Error) as e:
            kdrt.scene.decode_scene_point_cloud(bad)
        assert e.value.kind == "protocol"


def test_answer_buffers_are_reused_only_once_nothing_views_them():
    """_transport.BodyBuffers: a kept buffer is handed out again only when no view of it (a
    memoryview, a numpy array made from one) is alive; a larger answer replaces a free smaller
    buffer; at most `keep` buffers are kept."""
    pool = kdrt._transport.BodyBuffers(keep=2)
    first = pool.take(1000)
    first[:] = b"\1" * 1000
    held = np.frombuffer(first, dtype=np.uint8)
    del first
    second = pool.take(1000)  # the first is still viewed by `held`
    second[:] = b"\2" * 1000
    assert (held == 1).all() and len(pool._buffers) == 2
    third = pool.take(1000)  # both viewed: a buffer outside the pool
    third[:] = b"\3" * 1000
    assert (held == 1).all() and len(pool._buffers) == 2
    base = id(held.base.obj)  # the bytearray behind the first answer
    del held, third
    again = pool.take(500)
    assert id(again.obj) == base  # no view of it left: reused
    del again, second
    big = pool.take(3 << 20)  # larger than both: one free buffer gives its place
    assert len(big) == 3 << 20 and len(pool._buffers) == 2
    assert any(buf is big.obj for buf in pool._buffers)


def test_a_scans_arrays_survive_the_next_scans(server):
    """Scene.scan_lidar reads its answer into a reused buffer (_transport.read_pooled): an
    earlier scan's arrays, still held, keep their values through the scans after it, and every
    answer equals the same request read without the pool."""
    client, mesh, scene = _box_and_empty_scene(server)
    scene.add_triangles(mesh)
    scene.add_triangles(mesh, transform=[[0, -1, 0, 3], [1, 0, 0, 0.5], [0, 0, 1, 0]])
    scene.commit()
    path = client._t.api(f"/v1/scenes/{scene.id}/scan")
    scans = []
    for k in range(5):
        pose = [[1, 0, 0, 0.5 + 0.1 * k], [0, 1, 0, 0.5], [0, 0, 1, 0.5], [0, 0, 0, 1]]
        lidar = dict(azimuth_steps=64 + 16 * k, vertical_fov=(-40, 40), channels=16, pose=pose)
        got = scene.scan_lidar(**lidar)
        request = {"lidar": {"azimuth_steps": 64 + 16 * k, "returns": 1, "min_range": 0.0,
                             "vertical_fov": [-40.0, 40.0], "channels": 16, "pose": pose},
                   "format": "binary"}
        _, _, plain = client._t.request("POST", path, [json.dumps(request).encode()],
                                        "application/json")
        assert isinstance(plain, bytes)
        want = kdrt.scene.decode_scene_point_cloud(plain)
        assert want["range"].size > 100
        scans.append((got, {key: value.copy() for key, value in want.items()}))
        for held, expected in scans:
            for key in expected:
                assert np.array_equal(held[key], expected[key]), (k, key)
    assert len(client._t.bodies._buffers) <= kdrt._transport.POOLED_BUFFERS


def test_compact_scan_carries_what_kdrl_does(server):
    """record="ranges" (KDRB): the same ranges, prims and geometry ids bit for bit, the channel,
    azimuth and return indices implied by the beams, and points on the beams' rays that agree
    with KDRL's to rounding; an old client's request (no "format") still gets KDRL."""
    client, mesh, scene = _box_and_empty_scene(server)
    scene.add_triangles(mesh)
    scene.add_triangles(mesh, transform=[[0, -1, 0, 3], [1, 0, 0, 0.5], [0, 0, 1, 0]])
    for returns, pose in ((2, [[1, 0, 0, 0.5], [0, 1, 0, 0.5], [0, 0, 1, 0.5], [0, 0, 0, 1]]),
                          (1, [[0, -1, 0, 1.5], [1, 0, 0, 0.25], [0, 0, 1, 0.4], [0, 0, 0, 1]])):
        lidar = dict(azimuth_steps=96, vertical_fov=(-35, 30), channels=12, returns=returns,
                     pose=pose, max_range=50.0)
        full = scene.scan_lidar(**lidar, record="points")
        compact = scene.scan_lidar(**lidar, record="ranges")
        assert isinstance(compact, kdrt._scan.LidarScan)
        n = full["range"].shape[0]
        assert n > 400
        assert set(compact) == set(full) | {"beam"}
        for key in ("range", "primitive_ids", "geometry_ids", "channel", "azimuth_index",
                    "return_index"):
            assert np.array_equal(compact[key], full[key]), key
        assert set(np.unique(compact["geometry_ids"])) == {0, 1}
        assert compact["points"].dtype == np.float32 and compact["points"].shape == (n, 3)
        scale = np.maximum(1.0, np.abs(full["points"]))
        assert np.all(np.abs(compact["points"] - full["points"]) <= 1e-5 * scale)
    # The elevations given one by one, a single channel.
    one = scene.scan_lidar(azimuth_steps=32, elevation_deg=[0.0], pose=lidar["pose"],
                           record="ranges")
    full = scene.scan_lidar(azimuth_steps=32, elevation_deg=[0.0], pose=lidar["pose"])
    # The default is KDRL: the server's on-triangle points, bit for bit.
    assert not isinstance(full, kdrt._scan.LidarScan)
    assert np.array_equal(full["points"], scene.scan_lidar(
        azimuth_steps=32, elevation_deg=[0.0], pose=lidar["pose"], record="points")["points"])
    assert np.array_equal(one["range"], full["range"]) and one["range"].size > 0
    assert np.allclose(one["points"], full["points"], rtol=1e-5, atol=1e-5)
    # Negotiated: the raw answers to the same request without and with "format": "ranges".
    path = client._t.api(f"/v1/scenes/{scene.id}/scan")
    request = {"lidar": {"azimuth_steps": 16, "elevation_deg": [0.0]}}
    _, _, old = client._t.request("POST", path, [json.dumps(request).encode()],
                                  "application/json")
    assert old[:4] == b"KDRL"
    request["format"] = "ranges"
    _, _, new = client._t.request("POST", path, [json.dumps(request).encode()],
                                  "application/json")
    assert new[:4] == b"KDRB"
    assert len(new) < len(old) / 2
    for bad in (new[:-4], new[:20], new[:6] + b"\0\0" + new[8:], old):
        with pytest.raises(kdrt.Error) as e:
            kdrt._scan.decode_lidar_ranges(bad, request["lidar"], geometry_ids=True)
        assert e.value.kind == "protocol"
    with pytest.raises(kdrt.Error) as e:
        scene.scan_lidar(azimuth_steps=8, elevation_deg=[0.0], record="xyz")
    assert e.value.kind == "input" and "record" in e.value.detail


def test_geometry_ids_poses_and_revisions(server):
    client = kdrt.Client(server.url)
    v, t = _box()
    a = scene_a = kdrt.Scene(client)
    g0 = a.add_triangles(v, t)
    g1 = a.add_triangles(v, t, transform=np.array([[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 0],
                                                   [0, 0, 0, 1]]))
    assert (g0, g1) == (0, 1)
    hits = a.cast_rays(np.concatenate([_rays_at(0), _rays_at(3)]))
    assert (hits["geometry_ids"][:64] == 0).all() and (hits["geometry_ids"][64:] == 1).all()
    assert np.allclose(hits["t_hit"], 4.0)
    first = scene_a.revision
    # Move instance 1 up by 10 (one batch of one pose): its rays miss at the new revision...
    revision = a.set_transforms([g1], [[[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 10]]])
    assert revision == first + 1
    moved = a.cast_rays(_rays_at(3))
    assert (moved["geometry_ids"] == kdrt.NO_GEOMETRY).all() and np.isinf(moved["t_hit"]).all()
    # ...and answer as before at the pinned older revision.
    pinned = a.cast_rays(_rays_at(3), revision=first)
    assert (pinned["geometry_ids"] == 1).all()
    # A stale If-Match is refused.
    with pytest.raises(kdrt.Error) as e:
        a.set_transforms([g0], [np.eye(4)], if_revision=first)
    assert e.value.status == 412
    # Every hit along rays through both boxes (moved back in line).
    a.set_transform(g1, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -3], [0, 0, 0, 1]])
    all_hits = a.list_intersections(_rays_at(0, 8), max_hits=8)
    assert np.array_equal(np.diff(all_hits["ray_splits"].astype(np.int64)), np.full(8, 4))
    assert sorted(set(all_hits["geometry_ids"].tolist())) == [0, 1]
    # Distances with geometry ids.
    d = a.compute_closest_points(np.array([[0.5, 0.5, 2.0], [0.5, 0.5, -5.0]], np.float32))
    assert d["geometry_ids"].tolist() == [0, 1]
    assert np.allclose(d["distance"], [1.0, 2.0])


def test_refusals_name_the_instance_and_field(server):
    client, mesh, scene = _box_and_empty_scene(server)
    scene.add_triangles(mesh)
    scene.add_triangles("0" * 64)
    with pytest.raises(kdrt.Error) as e:
        scene.commit()
    assert e.value.status == 422
    assert "instances[1].mesh" in str(e.value) or "0" * 64 in e.value.detail
    bad = kdrt.Scene(client)
    bad.add_triangles(mesh, transform=[[1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0]])
    with pytest.raises(kdrt.Error) as e:
        bad.commit()
    assert e.value.status == 400 and "singular" in e.value.detail


def test_queries_past_the_servers_limit_go_in_chunks_of_one_revision():
    # The server takes 100 rays (and points) a request; 1000 go in chunks of 100 like the C++
    # client sends them: chunk 0 alone, then the rest on 3 connections, all pinned to the
    # revision chunk 0 answered from.
    server = Server("--max-rays", "100", "--max-distance-points", "100")
    try:
        with kdrt.Client(server.url, chunk_rays=100, connections=3) as client, \
                kdrt.Client(server.url) as whole:
            v, t = _box()
            mesh = client.upload(v, t)
            scene = kdrt.Scene(client)
            scene.add_triangles(mesh)
            g1 = scene.add_triangles(mesh, transform=[[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 0]])
            scene.commit()
            rays = np.concatenate([_rays_at(0, 500, seed=5), _rays_at(3, 500, seed=6)])
            # One request of 1000 rays is over the limit.
            with pytest.raises(kdrt.Error) as e:
                kdrt.Scene(whole, scene_id=scene.id).cast_rays(rays)
            assert e.value.status == 413
            hits = scene.cast_rays(rays)
            want = client.cast_rays(mesh, rays[:500])  # instance 0 is the mesh as it is
            assert hits["geometry_ids"].tolist() == [0] * 500 + [1] * 500
            assert np.array_equal(hits["t_hit"][:500], want["t_hit"])
            assert np.array_equal(hits["primitive_ids"][:500], want["primitive_ids"])
            assert (hits["t_hit"] == 4.0).all()
            assert np.array_equal(scene.test_occlusions(rays), np.ones(1000, bool))
            all_hits = scene.list_intersections(rays, max_hits=4)
            assert np.array_equal(np.diff(all_hits["ray_splits"].astype(np.int64)),
                                  np.full(1000, 2))
            assert np.array_equal(all_hits["ray_ids"], np.repeat(np.arange(1000), 2))
            assert np.array_equal(all_hits["geometry_ids"], np.repeat([0, 1], 1000))
            points = np.concatenate([rays[:, :3] - [0, 0, 3.5]]).astype(np.float32)
            d = scene.compute_closest_points(points)
            assert d["geometry_ids"].tolist() == [0] * 500 + [1] * 500
            assert np.allclose(d["distance"], 0.5)
            # Pinned: instance 1 moved away, the old revision still answers every chunk.
            first = scene.revision
            scene.set_transform(g1, [[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 50]])
            moved = scene.cast_rays(rays)
            assert (moved["geometry_ids"][500:] == kdrt.NO_GEOMETRY).all()
            pinned = scene.cast_rays(rays, revision=first)
            assert np.array_equal(pinned["geometry_ids"], hits["geometry_ids"])
            assert np.array_equal(pinned["t_hit"], hits["t_hit"])
    finally:
        server.stop()
