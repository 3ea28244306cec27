#!/usr/bin/env python3
"""Latency of POST /v1/meshes/{id}/scan over HTTP on loopback (issue 13, part 3).

    tests/bench/scan_latency.py BUILD_DIR [--requests 25] [--threads 2] [--mesh FILE]

Starts BUILD_DIR/server/kdrt-server (use a release build) with --threads THREADS on an
ephemeral port, uploads the mesh (default tests/data/bunny00.off), warms up, then times
REQUESTS sequential requests on one keep-alive connection for each case:
  lidar    64 channels (vertical_fov -25..15 deg) x 2048 azimuth steps, 1 and 2 returns, KDRL,
           beside the bunny (most beams miss), and inside a room: the bunny in a closed box
           (every beam returns)
  pinhole  640 x 480 depth, KDRZ (and with normals)
and prints median and p90 wall time per request (sending the JSON, tracing, receiving the whole
answer), answer bytes, and rays (and points) per second at the median. Standard library only.
"""

import argparse
import http.client
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))


def start_server(build, threads, workdir):
    port_file = os.path.join(workdir, "port")
    server = subprocess.Popen(
        [os.path.join(build, "server", "kdrt-server"), "--listen", "127.0.0.1:0", "--port-file",
         port_file, "--cache-dir", os.path.join(workdir, "cache"), "--threads", str(threads),
         "--log-level", "warn"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(600):
        try:
            port = int(open(port_file).read().strip())
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=5) as r:
                if r.status == 200:
                    return server, port
        except (OSError, ValueError):
            time.sleep(0.05)
    server.kill()
    sys.exit("kdrt-server did not become ready")


def upload(port, path, data=None, media_type="application/x-off"):
    if data is None:
        with open(path, "rb") as f:
            data = f.read()
    req = urllib.request.Request(f"http://127.0.0.1:{port}/v1/meshes", data=data, method="POST",
                                 headers={"Content-Type": media_type})
    with urllib.request.urlopen(req, timeout=600) as r:
        return json.loads(r.read())


def room_obj(off_path, scale):
    """The OFF mesh plus a closed box around it, `scale` times its size, as OBJ text."""
    words = open(off_path).read().split()
    assert words[0] == "OFF"
    nv, nf = int(words[1]), int(words[2])
    vs = [tuple(float(w) for w in words[4 + 3 * i:7 + 3 * i]) for i in range(nv)]
    k = 4 + 3 * nv
    faces = []
    for _ in range(nf):
        n = int(words[k])
        faces.append([int(w) for w in words[k + 1:k + 1 + n]])
        k += 1 + n
    lo = [min(v[a] for v in vs) for a in range(3)]
    hi = [max(v[a] for v in vs) for a in range(3)]
    c = [(a + b) / 2 for a, b in zip(lo, hi)]
    h = scale * max(b - a for a, b in zip(lo, hi)) / 2
    box = [(c[0] + sx * h, c[1] + sy * h, c[2] + sz * h)
           for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (1, 3, 7, 5), (0, 4, 6, 2)]
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vs + box]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in faces]
    for q in quads:
        a, b, cc, d = (nv + i + 1 for i in q)
        lines += [f"f {a} {b} {cc}", f"f {a} {cc} {d}"]
    return "\n".join(lines) + "\n"


def percentile(values, p):
    s = sorted(values)
    k = (len(s) - 1) * p
    lo, hi = math.floor(k), math.ceil(k)
    return s[lo] + (s[hi] - s[lo]) * (k - lo)


def time_case(conn, path, body, requests):
    times, size = [], 0
    payload = json.dumps(body).encode()
    for i in range(requests + 2):  # two warm-up requests
        start = time.perf_counter()
        conn.request("POST", path, payload, {"Content-Type": "application/json"})
        answer = conn.getresponse()
        data = answer.read()
        elapsed = time.perf_counter() - start
        if answer.status != 200:
            sys.exit(f"{answer.status}: {data[:300]!r}")
        if i >= 2:
            times.append(elapsed)
        size = len(data)
    return times, data


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("build")
    parser.add_argument("--requests", type=int, default=25)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--mesh", default=os.path.join(HERE, "..", "data", "bunny00.off"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="kdrt-scan-bench-") as workdir:
        server, port = start_server(args.build, args.threads, workdir)
        try:
            mesh = upload(port, args.mesh)
            lo, hi = mesh["bounds"]["min"], mesh["bounds"]["max"]
            centre = [(a + b) / 2 for a, b in zip(lo, hi)]
            radius = math.dist(lo, hi) / 2
            # The lidar beside the bunny, its z up along world +z; the camera in front (+z).
            lidar_pose = [[1, 0, 0, centre[0] + 1.5 * radius], [0, 1, 0, centre[1]],
                          [0, 0, 1, centre[2]], [0, 0, 0, 1]]
            cam_pose = [[1, 0, 0, centre[0]], [0, -1, 0, centre[1]],
                        [0, 0, -1, centre[2] + 2.5 * radius], [0, 0, 0, 1]]
            cases = [
                ("lidar 64 x 2048, 1 return", 64 * 2048, {"lidar": {
                    "vertical_fov": [-25, 15], "channels": 64, "azimuth_steps": 2048,
                    "returns": 1, "pose": lidar_pose}}),
                ("lidar 64 x 2048, 2 returns", 64 * 2048, {"lidar": {
                    "vertical_fov": [-25, 15], "channels": 64, "azimuth_steps": 2048,
                    "returns": 2, "pose": lidar_pose}}),
                ("pinhole 640 x 480 depth", 640 * 480, {"pinhole": {
                    "intrinsics": {"fx": 525, "fy": 525, "cx": 319.5, "cy": 239.5,
                                   "width": 640, "height": 480}, "pose": cam_pose}}),
                ("pinhole 640 x 480 depth + normals", 640 * 480, {"pinhole": {
                    "intrinsics": {"fx": 525, "fy": 525, "cx": 319.5, "cy": 239.5,
                                   "width": 640, "height": 480}, "pose": cam_pose,
                    "normals": True}}),
            ]
            room = upload(port, None, room_obj(args.mesh, 4.0).encode(), "model/obj")
            room_pose = [[1, 0, 0, centre[0] + 1.2 * radius], [0, 1, 0, centre[1]],
                         [0, 0, 1, centre[2]], [0, 0, 0, 1]]
            cases.insert(2, ("lidar 64 x 2048 in a room, 2 returns", 64 * 2048, {"lidar": {
                "vertical_fov": [-25, 15], "channels": 64, "azimuth_steps": 2048, "returns": 2,
                "pose": room_pose}}, room["id"]))
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=600)
            print(f"mesh {os.path.basename(args.mesh)}: {mesh['triangles']} triangles; "
                  f"kdrt-server --threads {args.threads}; {args.requests} requests per case")
            for name, rays, body, *mesh_id in cases:
                path = f"/v1/meshes/{(mesh_id or [mesh['id']])[0]}/scan"
                times, data = time_case(conn, path, body, args.requests)
                med, p90 = statistics.median(times), percentile(times, 0.9)
                extra = ""
                if data[:4] == b"KDRL":
                    points = int.from_bytes(data[8:12], "little")
                    extra = f", {points} points, {points / med / 1e6:.2f} M points/s"
                elif data[:4] == b"KDRZ":
                    w, h = int.from_bytes(data[8:12], "little"), int.from_bytes(data[12:16],
                                                                                 "little")
                    prims = memoryview(data)[16 + 4 * w * h:16 + 8 * w * h].cast("I")
                    hit = sum(1 for p in prims if p != 0xFFFFFFFF)
                    extra = f", {hit} pixels hit"
                print(f"{name:36s} median {med * 1e3:7.1f} ms  p90 {p90 * 1e3:7.1f} ms  "
                      f"{len(data) / 1e6:6.2f} MB  {rays / med / 1e6:5.2f} M rays/s{extra}")
            conn.close()
        finally:
            server.terminate()
            server.wait()


if __name__ == "__main__":
    main()
