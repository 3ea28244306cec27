#!/usr/bin/python3
"""kdrt_python_bench: the Python client (client/python, package kdrt) against the C++ client on
the same 1M-ray batches, on one kdrt-server.

For each ray kind (primary, diffuse by default) the bunny's KDRR ray set is made by `kdrt rays`
(cut to --rays rays), then, alternating for --rounds rounds: `kdrt bench-remote --rays FILE`
(kdrt::Client: one untimed pass, --reps timed passes, median) and the Python client's
cast_rays on the same rays (one untimed pass, --reps timed passes, median), both with their
default chunking (65536 rays per request, 4 connections). Prints one JSON object per kind and
round: cpp_mrays, python_mrays, ratio = python / cpp, and same_hits (the answers compared byte
for byte). A benchmark: it asserts nothing about time.

    tests/bench/kdrt_python_bench.py [--build build/release] [--server URL] [--threads 2]
                                     [--rays 1048576] [--reps 5] [--rounds 2]
                                     [--kinds primary,diffuse]

Without --server it starts build/release/server/kdrt-server on an ephemeral port with --threads.
"""

import argparse
import json
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(ROOT, "client", "python"))
sys.path.insert(0, os.path.join(ROOT, "tests", "client", "python"))

import numpy as np  # noqa: E402

import kdrt  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--build", default=os.path.join(ROOT, "build", "release"))
    parser.add_argument("--server")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rays", type=int, default=1 << 20)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--kinds", default="primary,diffuse")
    args = parser.parse_args()
    cli = os.path.join(args.build, "client", "kdrt")
    mesh_file = os.path.join(ROOT, "tests", "data", "bunny00.off")

    server = None
    url = args.server
    if url is None:
        os.environ.setdefault("KDRT_SERVER_BINARY",
                              os.path.join(args.build, "server", "kdrt-server"))
        from conftest import Server  # the test fixture's server process
        server = Server("--threads", str(args.threads), "--max-inflight", "1000")
        url = server.url
    try:
        client = kdrt.Client(url)
        mesh = client.upload(mesh_file)
        work = tempfile.mkdtemp(prefix="kdrt-python-bench-")
        for kind in args.kinds.split(","):
            path = os.path.join(work, kind + ".kdrr")
            for res in range(1024, 8193, 128):  # diffuse rays exist only where primary ones hit
                subprocess.run([cli, "rays", mesh_file, "-o", path, "--kind", kind, "--res",
                                str(res)], check=True, capture_output=True)
                data = open(path, "rb").read()
                count = struct.unpack("<I", data[8:12])[0]
                if count >= args.rays:
                    break
            # Cut to exactly --rays rays, as a KDRR file again for the C++ client.
            records = np.frombuffer(data, dtype="<f4", offset=16).reshape(count, 8)[:args.rays]
            with open(path, "wb") as f:
                f.write(data[:8] + struct.pack("<II", args.rays, 0) + records.tobytes())
            rays = np.ascontiguousarray(records[:, [0, 1, 2, 4, 5, 6, 3, 7]])
            for round_index in range(args.rounds):
                done = subprocess.run(
                    [cli, "--server", url, "bench-remote", mesh.id, "--rays", path, "--reps",
                     str(args.reps), "--json"], check=True, capture_output=True, text=True)
                cpp = json.loads(done.stdout.strip().splitlines()[-1])
                hits = client.cast_rays(mesh, rays)  # untimed
                seconds = []
                for _ in range(args.reps):
                    start = time.perf_counter()
                    hits = client.cast_rays(mesh, rays)
                    seconds.append(time.perf_counter() - start)
                python_mrays = args.rays / statistics.median(seconds) / 1e6
                answer = os.path.join(work, kind + ".kdrh")
                subprocess.run([cli, "--server", url, "trace", mesh.id, path, "-o", answer],
                               check=True, capture_output=True)
                t = hits["t_hit"]
                mine = np.empty((t.size, 4), dtype="<f4")
                mine[:, 0] = t
                mine.view("<u4")[:, 1] = hits["primitive_ids"]
                mine[:, 2:4] = hits["primitive_uvs"]
                same = open(answer, "rb").read()[16:] == mine.tobytes()
                print(json.dumps({
                    "measure": "python_client", "rays": kind, "count": args.rays,
                    "round": round_index, "reps": args.reps,
                    "cpp_mrays": round(cpp["mrays_per_s"], 2),
                    "python_mrays": round(python_mrays, 2),
                    "ratio": round(python_mrays / cpp["mrays_per_s"], 3),
                    "same_hits": same}), flush=True)
    finally:
        if server is not None:
            server.stop()


if __name__ == "__main__":
    main()
