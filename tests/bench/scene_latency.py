#!/usr/bin/python3
"""A moving sensor over HTTP (issue 26): a scene of INSTANCES instances has every pose changed,
then a 64 x 2048 lidar scan is taken, end to end over loopback from the Python client (kdrt.Scene),
FRAMES frames in a row on one keep-alive connection.

    tests/bench/scene_latency.py BUILD_DIR [--frames 25] [--instances 1000] [--threads 2]
                                           [--mesh FILE] [--cache-dir DIR]
                                           [--record ranges|points] [--scene-sync commit|none]

Starts BUILD_DIR/server/kdrt-server (a release build) on an ephemeral port, uploads the mesh
(default tests/data/bunny00.off, scaled into each instance's cell by its transform), creates the
scene (instances on a grid around the sensor, each turned by its own angle), warms up with one
frame, then per frame: one KDRX pose batch moving every instance (a new revision, stored durably
before the answer), then the lidar scan of the new revision (with geometry ids: KDRL, the Python
client's default, or the compact KDRB record with --record ranges). Prints the median and p90 of the frame, the pose update and
the scan, the returns per scan, how many distinct geometry ids they hit, and the server's CPU
use over the frames (cpu_util: CPU seconds per second, about 2 with 2 threads busy). With KDRB the points
are made by the client on first access, after the frame: that is timed on its own line. The cache directory decides what an fsync costs (default: a temp
directory); --scene-sync none starts the server without the flush of each revision (config
scene_sync). No timing is asserted.
"""

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "client", "python"))

import kdrt  # noqa: E402


def start_server(build, threads, cache_dir, workdir, extra=()):
    port_file = os.path.join(workdir, "port")
    server = subprocess.Popen(
        [os.path.join(build, "server", "kdrt-server"), "--listen", "127.0.0.1:0", "--port-file",
         port_file, "--cache-dir", cache_dir, "--threads", str(threads), "--log-level", "warn",
         *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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


def poses(n, frame):
    """Instance k on a ring grid around the origin, turned about z by its own angle that
    advances each frame; scale 1.5 (the bunny is about 1 unit)."""
    k = np.arange(n)
    side = int(np.ceil(np.sqrt(n)))
    x = (k % side - side / 2) * 3.0
    y = (k // side - side / 2) * 3.0
    a = 0.01 * frame + 0.37 * k
    c, s = np.cos(a) * 1.5, np.sin(a) * 1.5
    t = np.zeros((n, 3, 4))
    t[:, 0, 0], t[:, 0, 1], t[:, 0, 3] = c, -s, x
    t[:, 1, 0], t[:, 1, 1], t[:, 1, 3] = s, c, y
    t[:, 2, 2], t[:, 2, 3] = 1.5, 0.0
    return t


def cpu_seconds(pid):
    """User plus system CPU seconds of process `pid` so far (all its threads)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def pct(values, p):
    s = sorted(values)
    return s[min(len(s) - 1, int(round(p / 100 * (len(s) - 1))))]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("build")
    ap.add_argument("--frames", type=int, default=25)
    ap.add_argument("--instances", type=int, default=1000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--mesh", default=os.path.join(HERE, "..", "data", "bunny00.off"))
    ap.add_argument("--cache-dir")
    ap.add_argument("--record", choices=("ranges", "points"), default="points",
                    help="the scan's answer: KDRL (points, the default) or KDRB (ranges)")
    ap.add_argument("--scene-sync", choices=("commit", "none"),
                    help="the server's scene_sync (default: the server's default, commit)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as work:
        cache = args.cache_dir or os.path.join(work, "cache")
        extra = ("--scene-sync", args.scene_sync) if args.scene_sync else ()
        server, port = start_server(args.build, args.threads, cache, work, extra)
        try:
            client = kdrt.Client(f"http://127.0.0.1:{port}", connections=1)
            mesh = client.upload(args.mesh)
            scene = kdrt.Scene(client)
            first = poses(args.instances, 0)
            for k in range(args.instances):
                scene.add_triangles(mesh, transform=first[k])
            t0 = time.perf_counter()
            scene.commit()
            create_s = time.perf_counter() - t0
            ids = np.arange(args.instances)
            lidar = dict(azimuth_steps=2048, vertical_fov=(-25, 15), channels=64,
                         pose=[[1, 0, 0, 0.7], [0, 1, 0, 0.3], [0, 0, 1, 0.2], [0, 0, 0, 1]],
                         max_range=120.0, record=args.record)
            scene.set_transforms(ids, poses(args.instances, 1))  # warm-up frame
            scene.scan_lidar(**lidar)["points"]
            frame_s, pose_s, scan_s, points_s = [], [], [], []
            returns, geoms = 0, 0
            cpu0, wall0 = cpu_seconds(server.pid), time.perf_counter()
            for f in range(args.frames):
                p = poses(args.instances, f + 2)
                t0 = time.perf_counter()
                scene.set_transforms(ids, p)
                t1 = time.perf_counter()
                cloud = scene.scan_lidar(**lidar)
                t2 = time.perf_counter()
                pose_s.append(t1 - t0)
                scan_s.append(t2 - t1)
                frame_s.append(t2 - t0)
                returns = cloud["range"].shape[0]
                geoms = len(np.unique(cloud["geometry_ids"]))
                t3 = time.perf_counter()
                assert cloud["points"].shape == (returns, 3)
                points_s.append(time.perf_counter() - t3)
            # The server's CPU use over the frames: about the server threads' count when its
            # workers run (under chrt a starved worker shows as less; tests/bench/README.md).
            cpu_util = (cpu_seconds(server.pid) - cpu0) / (time.perf_counter() - wall0)
            print(f"scene of {args.instances} instances of {mesh.triangles} triangles, "
                  f"created in {create_s * 1e3:.1f} ms; {args.frames} frames, server threads "
                  f"{args.threads}, cache {cache}, record {args.record}"
                  + (f", scene_sync {args.scene_sync}" if args.scene_sync else ""))
            for name, values in (("frame", frame_s), ("pose update", pose_s),
                                 ("lidar 64x2048", scan_s),
                                 ("points (after)", points_s)):
                print(f"  {name:14s} median {statistics.median(values) * 1e3:7.2f} ms   "
                      f"p90 {pct(values, 90) * 1e3:7.2f} ms")
            print(f"  returns per scan {returns}, distinct geometry ids hit {geoms}, "
                  f"last revision {scene.revision}, server cpu_util {cpu_util:.2f}")
        finally:
            server.terminate()
            server.wait(timeout=30)


if __name__ == "__main__":
    main()
