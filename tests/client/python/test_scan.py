"""Client.scan_pinhole / scan_lidar / scan_bytes against the kdrt CLI (the C++ client) on the
bunny: the arrays are the bytes of the CLI's KDRZ / KDRL files (read here with numpy from the
layout in proto/FORMATS.md), the PLY is the CLI's byte for byte, depth and range agree, and bad
input is refused naming the field."""

import numpy as np
import pytest

import kdrt


def look_pose(eye, target):
    """Camera-to-world, OpenCV axes (z forward, y down), world +y up."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def pose_text(pose):
    return ",".join(repr(float(v)) for v in np.asarray(pose).reshape(-1))


def read_kdrz(path):
    body = path.read_bytes()
    assert body[:4] == b"KDRZ"
    flags = int(np.frombuffer(body, "<u2", 1, 6)[0])
    w, h = (int(v) for v in np.frombuffer(body, "<u4", 2, 8))
    n = w * h
    depth = np.frombuffer(body, "<f4", n, 16).reshape(h, w)
    prim = np.frombuffer(body, "<u4", n, 16 + 4 * n).reshape(h, w)
    normals = np.frombuffer(body, "<f4", 3 * n, 16 + 8 * n).reshape(h, w, 3) if flags & 2 else None
    return flags, depth, prim, normals


@pytest.fixture(scope="module")
def camera(bunny):
    lo, hi = bunny.bounds
    centre = (lo + hi) / 2
    radius = np.linalg.norm(hi - lo) / 2
    pose = look_pose(centre + [0.5 * radius, 0.3 * radius, 2.5 * radius], centre)
    return {"pose": pose, "intrinsics": (70.0, 70.0, 31.5, 24.0, 64, 48), "centre": centre,
            "radius": radius}


def test_pinhole_arrays_are_the_cpp_clients(client, server, bunny, cli, camera, tmp_path):
    out = tmp_path / "depth.kdrz"
    cli("--server", server.url, "scan", bunny.id, "--pinhole", "-o", str(out), "--intrinsics",
        "70,70,31.5,24", "--size", "64x48", "--pose", pose_text(camera["pose"]), "--normals")
    flags, depth, prim, normals = read_kdrz(out)
    assert flags == 2
    got = client.scan_pinhole(bunny, intrinsics=camera["intrinsics"], pose=camera["pose"],
                              normals=True)
    assert set(got) == {"depth", "prim", "normals"}
    assert got["depth"].shape == (48, 64) and got["depth"].dtype == np.float32
    assert got["prim"].dtype == np.uint32 and got["normals"].shape == (48, 64, 3)
    assert got["depth"].tobytes() == depth.tobytes()
    assert np.array_equal(got["prim"], prim)
    assert got["normals"].tobytes() == normals.tobytes()
    hit = got["prim"] != kdrt.NO_HIT
    assert 0.1 < hit.mean() < 0.9
    assert np.all(np.isinf(got["depth"][~hit]))
    assert np.allclose(np.linalg.norm(got["normals"][hit], axis=1), 1, atol=1e-5)
    assert np.all(got["normals"][~hit] == 0)


def test_depth_is_range_times_the_cosine(client, bunny, camera):
    fx, fy, cx, cy, w, h = camera["intrinsics"]
    depth = client.scan_pinhole(bunny, intrinsics=camera["intrinsics"], pose=camera["pose"])
    rng = client.scan_pinhole(bunny, intrinsics=camera["intrinsics"], pose=camera["pose"],
                              output="range")
    assert set(rng) == {"range", "prim"}
    assert np.array_equal(depth["prim"], rng["prim"])
    i, j = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    cosine = 1 / np.sqrt(((i - cx) / fx) ** 2 + ((j - cy) / fy) ** 2 + 1)
    hit = depth["prim"] != kdrt.NO_HIT
    assert np.allclose(depth["depth"][hit], rng["range"][hit] * cosine[hit], rtol=1e-6)
    assert np.all(depth["depth"][hit] <= rng["range"][hit])


def test_look_at_camera_is_the_cpp_clients(client, server, bunny, cli, camera, tmp_path):
    eye = camera["centre"] + [0, 0, 3 * camera["radius"]]
    out = tmp_path / "look.kdrz"
    cli("--server", server.url, "scan", bunny.id, "--pinhole", "-o", str(out), "--eye",
        ",".join(repr(float(v)) for v in eye), "--look-at",
        ",".join(repr(float(v)) for v in camera["centre"]), "--size", "40x30", "--range")
    _, rng, prim, _ = read_kdrz(out)
    got = client.scan_pinhole(bunny, camera={"eye": eye, "look_at": camera["centre"]}, width=40,
                              height=30, output="range")
    assert got["range"].tobytes() == rng.tobytes()
    assert np.array_equal(got["prim"], prim)
    assert (prim != kdrt.NO_HIT).any()


def test_lidar_points_are_the_cpp_clients(client, server, bunny, cli, camera, tmp_path):
    pose = np.eye(4)
    pose[:3, 3] = camera["centre"] + [1.6 * camera["radius"], 0, 0.2 * camera["radius"]]
    kdrl, ply = tmp_path / "cloud.kdrl", tmp_path / "cloud.ply"
    args = ["--channels", "16", "--vertical-fov", "-30,20", "--azimuth-steps", "256",
            "--returns", "2", "--pose", pose_text(pose)]
    cli("--server", server.url, "scan", bunny.id, "--lidar", "-o", str(kdrl), *args)
    cli("--server", server.url, "scan", bunny.id, "--lidar", "-o", str(ply), *args)
    points = client.scan_lidar(bunny, azimuth_steps=256, vertical_fov=(-30, 20), channels=16,
                               returns=2, pose=pose)
    assert points.dtype == kdrt.LIDAR_POINT_DTYPE
    assert len(points) > 50
    body = kdrl.read_bytes()
    assert body[:4] == b"KDRL" and int(np.frombuffer(body, "<u4", 1, 8)[0]) == len(points)
    assert points.tobytes() == body[32:]
    # Beam order: azimuth-major, returns nearest first.
    beam = points["azimuth_index"].astype(np.int64) * 16 + points["channel"]
    assert np.all(np.diff(beam) >= 0)
    second = points["return_index"] == 1
    assert np.all(points["range"][second] >= points["range"][np.flatnonzero(second) - 1])
    # The range is the distance from the sensor to the point.
    d = np.linalg.norm(np.stack([points["x"], points["y"], points["z"]], 1) - pose[:3, 3], axis=1)
    assert np.allclose(d, points["range"], rtol=1e-4)
    request = {"lidar": {"vertical_fov": [-30, 20], "channels": 16, "azimuth_steps": 256,
                         "returns": 2, "pose": pose.tolist()}, "format": "ply"}
    assert client.scan_bytes(bunny, request) == ply.read_bytes()


def test_compact_lidar_scan_carries_what_kdrl_does(client, bunny, camera):
    """record="ranges" (KDRB) on a mesh: the same ranges, prims, channels, azimuth and return
    indices as KDRL bit for bit, and points on the beams' rays that agree to rounding."""
    pose = np.eye(4)
    pose[:3, 3] = camera["centre"] + [1.6 * camera["radius"], 0, 0.2 * camera["radius"]]
    lidar = dict(azimuth_steps=256, vertical_fov=(-30, 20), channels=16, returns=2, pose=pose)
    full = client.scan_lidar(bunny, **lidar)
    compact = client.scan_lidar(bunny, **lidar, record="ranges")
    assert isinstance(compact, kdrt._scan.LidarScan)
    assert len(full) > 50 and compact["range"].shape == (len(full),)
    for key, field in (("range", "range"), ("primitive_ids", "prim"), ("channel", "channel"),
                       ("azimuth_index", "azimuth_index"), ("return_index", "return_index")):
        assert np.array_equal(compact[key], full[field]), key
    xyz = np.stack([full["x"], full["y"], full["z"]], 1)
    assert np.all(np.abs(compact["points"] - xyz) <= 1e-5 * np.maximum(1.0, np.abs(xyz)))
    with pytest.raises(kdrt.Error) as e:
        client.scan_lidar(bunny, **lidar, record="xyz")
    assert e.value.kind == "input" and "record" in e.value.detail


def test_scans_arrays_survive_the_next_scans(client, bunny, camera):
    """scan_pinhole / scan_lidar read their answers into the client's reused buffers
    (_transport.read_pooled): an earlier scan's arrays, still held, keep their values through
    the scans after it, and each equals the same request's answer read as bytes (scan_bytes)."""
    scans = []
    for k in range(6):
        pose = np.eye(4)
        pose[:3, 3] = camera["centre"] + [(1.4 + 0.1 * k) * camera["radius"], 0, 0]
        lidar = {"vertical_fov": [-30, 20], "channels": 16, "azimuth_steps": 64 + 32 * k,
                 "returns": 1, "pose": pose.tolist()}
        record = "ranges" if k % 3 == 2 else "points"
        got = client.scan_lidar(bunny, azimuth_steps=64 + 32 * k, vertical_fov=(-30, 20),
                                channels=16, pose=pose, record=record)
        request = {"lidar": lidar, "format": kdrt._scan.lidar_format(record)}
        plain = client.scan_bytes(bunny, request)
        assert isinstance(plain, bytes)
        if record == "ranges":
            want = kdrt._scan.decode_lidar_ranges(plain, lidar)
            got = {key: got[key] for key in ("range", "primitive_ids")}
            want = {key: want[key].copy() for key in ("range", "primitive_ids")}
        else:
            want = kdrt._scan.decode_point_cloud(plain).copy()
        assert len(want["range"]) > 20
        scans.append((got, want))
        eye = camera["centre"] + [0.4 * camera["radius"], 0.2 * k * camera["radius"],
                                  2.5 * camera["radius"]]
        image = client.scan_pinhole(bunny, intrinsics=camera["intrinsics"],
                                    pose=look_pose(eye, camera["centre"]))
        request = {"pinhole": kdrt._scan.pinhole_request(
            camera["intrinsics"], look_pose(eye, camera["centre"]), None, None, None, "depth",
            False, None, None), "format": "binary"}
        want = kdrt._scan.decode_depth_image(client.scan_bytes(bunny, request))
        scans.append((image, {key: value.copy() for key, value in want.items()}))
        for held, expected in scans:
            if isinstance(expected, np.ndarray):
                assert held.tobytes() == expected.tobytes(), k
            else:
                for key in expected:
                    assert np.array_equal(held[key], expected[key]), (k, key)
    assert len(client._t.bodies._buffers) <= kdrt._transport.POOLED_BUFFERS


def test_errors_name_the_field(client, bunny, camera):
    bad = np.array(camera["pose"])
    bad[:3, :3] *= 2
    with pytest.raises(kdrt.Error) as e:
        client.scan_pinhole(bunny, intrinsics=camera["intrinsics"], pose=bad)
    assert e.value.status == 400 and '"pinhole.pose"' in e.value.detail
    with pytest.raises(kdrt.Error) as e:
        client.scan_lidar(bunny, azimuth_steps=8, elevation_deg=[0], returns=0)
    assert e.value.status == 400 and '"lidar.returns"' in e.value.detail
    with pytest.raises(kdrt.Error) as e:
        client.scan_pinhole(bunny, intrinsics=(0, 1, 1, 1, 4, 4), pose=np.eye(4))
    assert '"pinhole.intrinsics.fx"' in e.value.detail
    with pytest.raises(kdrt.Error) as e:
        client.scan_pinhole(bunny, intrinsics=camera["intrinsics"], pose=np.eye(3))
    assert e.value.kind == "input" and "4 x 4" in e.value.detail
    with pytest.raises(kdrt.Error) as e:
        client.scan_lidar(bunny, azimuth_steps=8)
    assert e.value.kind == "input"
