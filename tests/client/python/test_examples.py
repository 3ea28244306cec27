"""The examples in client/python/examples run as a user runs them (Debian's python3, against a
real server) and write what they say they write."""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np

import kdrt

EXAMPLES = os.path.join(os.path.dirname(os.path.abspath(kdrt.__file__)), os.pardir, "examples")


def run(name, *args):
    done = subprocess.run([sys.executable, os.path.join(EXAMPLES, name), *args],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def load(name):
    spec = importlib.util.spec_from_file_location(name[:-3], os.path.join(EXAMPLES, name))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_depth_image_png(server, data_dir, tmp_path):
    out = tmp_path / "depth.png"
    summary = run("depth_image.py", os.path.join(data_dir, "bunny00.off"), "--server",
                  server.url, "--size", "96", "--out", str(out))
    image = kdrt.read_png(out.read_bytes())
    assert image.shape == (96, 96, 1) and image.dtype == np.uint8
    assert 0 < summary["hits"] < 96 * 96
    assert int((image > 0).sum()) == summary["hits"]   # every hit is lit, every miss black
    assert image.max() == 255 and 0 < summary["near"] < summary["far"]


def test_lidar_scan_ply(server, data_dir, tmp_path, bunny):
    out = tmp_path / "scan.ply"
    summary = run("lidar_scan.py", os.path.join(data_dir, "bunny00.off"), "--server",
                  server.url, "--channels", "16", "--azimuths", "512", "--out", str(out))
    data = out.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    count = int(next(line for line in header if line.startswith("element vertex")).split()[2])
    assert count == summary["points"] and 0 < count < summary["rays"] == 16 * 512
    cloud = np.frombuffer(data, offset=end, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                   ("range", "<f4"), ("ring", "<u4"),
                                                   ("triangle", "<u4")])
    assert cloud.size == count
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    slack = 1e-4 * np.linalg.norm(bunny.bounds[1] - bunny.bounds[0])
    assert np.all(points >= bunny.bounds[0] - slack) and np.all(points <= bunny.bounds[1] + slack)
    assert np.all(cloud["ring"] < 16) and np.all(cloud["triangle"] < bunny.triangles)
    assert np.all(cloud["range"] > 0)


def test_occlusion_between_points(server, data_dir, client, bunny):
    summary = run("occlusion.py", os.path.join(data_dir, "bunny00.off"), "--server",
                  server.url, "--points", "500", "--seed", "3")
    example = load("occlusion.py")
    light = np.array(summary["light"])
    rays = example.segment_rays(example.points_under(bunny.bounds, 500, 3), light)
    # The oracle: a closest-hit query; a segment is blocked when its first hit is within it.
    blocked = client.cast_rays(bunny, rays)["t_hit"] <= rays[:, 7]
    assert summary["visible"] == int((~blocked).sum())
    assert 0 < summary["visible"] < 500
