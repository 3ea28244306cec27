#!/usr/bin/env python3
"""What nginx (docker/nginx/ routing) adds in front of kdrt-server, on loopback.

Starts one kdrt-server (replica r0) and nginx in front of it, uploads tests/data/bunny00.off, then
measures the same requests direct and through nginx, interleaved (A, B, A, B, ...) so drift and
noise hit both alike:
  - latency p50/p99 of 1-ray and 1000-ray KDRR batches (keep-alive connections);
  - throughput of 1M-ray batches (a 32 MiB body, a 16 MiB answer), median of --reps.
Prints one line per measurement. Usage (after a Release build):
  python3 tests/bench/nginx_overhead.py [--build build/release] [--requests 2000] [--reps 5]
"""
import argparse
import http.client
import json
import os
import pathlib
import random
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(port, path="/readyz", timeout=30):
    deadline = time.time() + timeout
    while time.time() < deadline:
        try:
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=1)
            c.request("GET", path)
            if c.getresponse().status == 200:
                return
        except OSError:
            pass
        time.sleep(0.05)
    raise RuntimeError(f"nothing answers {path} on port {port}")


def rays_body(count, seed):
    rng = random.Random(seed)
    out = bytearray(b"KDRR" + struct.pack("<HHII", 1, 0, count, 0))
    for _ in range(count):
        # From a sphere around the bunny (bounds about [-0.1, 0.1]^3) towards its middle.
        o = [rng.uniform(-1, 1) for _ in range(3)]
        d = [-c + rng.uniform(-0.05, 0.05) for c in o]
        out += struct.pack("<8f", o[0], o[1], o[2], 0.0, d[0], d[1], d[2], float("inf"))
    return bytes(out)


def post(conn, path, body):
    conn.request("POST", path, body, {"Content-Type": "application/x-kdrt-rays"})
    res = conn.getresponse()
    data = res.read()
    if res.status != 200:
        raise RuntimeError(f"{path}: {res.status} {data[:200]!r}")
    return data


def percentile(samples, p):
    s = sorted(samples)
    return s[min(len(s) - 1, int(p / 100 * len(s)))]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--build", default=str(ROOT / "build" / "release"))
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    server_bin = pathlib.Path(args.build) / "server" / "kdrt-server"
    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="kdrt-nginx-bench-"))
    procs = []
    try:
        port = free_port()
        procs.append(subprocess.Popen(
            [str(server_bin), "--listen", f"127.0.0.1:{port}", "--cache-dir", str(tmp / "store"),
             "--replica", "r0", "--log-level", "warn"], stderr=open(tmp / "server.log", "w")))
        wait_http(port)
        nport = free_port()
        up = f"127.0.0.1:{port}"
        conf = f"""{'user root;' if os.geteuid() == 0 else ''}
daemon off;
worker_processes 1;
pid {tmp}/nginx.pid;
error_log {tmp}/nginx.log warn;
events {{ worker_connections 1024; }}
http {{
    access_log off;
    client_body_temp_path {tmp}/body;
    proxy_temp_path {tmp}/proxy;
    include {ROOT}/docker/nginx/kdrt-http.conf;
    upstream kdrt_mesh {{ hash $kdrt_route_key consistent; server {up}; keepalive 16; keepalive_timeout 1s; }}
    upstream kdrt_any {{ least_conn; server {up}; keepalive 16; keepalive_timeout 1s; }}
    upstream kdrt_replica_r0 {{ server {up}; keepalive 4; keepalive_timeout 1s; }}
    map $kdrt_job_replica $kdrt_job_upstream {{ default kdrt_any; r0 kdrt_replica_r0; }}
    server {{ listen 127.0.0.1:{nport}; include {ROOT}/docker/nginx/kdrt-locations.conf; }}
}}
"""
        (tmp / "nginx.conf").write_text(conf)
        procs.append(subprocess.Popen([nginx, "-p", f"{tmp}/", "-e", f"{tmp}/nginx.log",
                                       "-c", str(tmp / "nginx.conf")]))
        wait_http(nport, "/healthz")

        c = http.client.HTTPConnection("127.0.0.1", nport)
        c.request("POST", "/v1/meshes", (ROOT / "tests" / "data" / "bunny00.off").read_bytes(),
                  {"Content-Type": "model/off"})
        res = c.getresponse()
        body = res.read()
        if res.status not in (200, 201):
            raise RuntimeError(f"upload: {res.status} {body!r}")
        summary = json.loads(body)
        mesh = summary["id"]
        path = f"/v1/meshes/{mesh}/intersect"
        direct = http.client.HTTPConnection("127.0.0.1", port)
        proxied = http.client.HTTPConnection("127.0.0.1", nport)
        # kdrt-server closes idle keep-alive connections after keep_alive_timeout_s (2 s) and
        # after 1000 requests: http.client reconnects transparently, on both sides alike.
        print(f"kdrt-server {up}, nginx 127.0.0.1:{nport}, mesh {mesh} (bunny00.off, "
              f"{summary['triangles']} triangles)")
        for rays in (1, 1000):
            batch = rays_body(rays, rays)
            for conn in (direct, proxied):
                for _ in range(50):
                    post(conn, path, batch)  # warm-up
            times = {"direct": [], "nginx": []}
            for _ in range(args.requests):
                for name, conn in (("direct", direct), ("nginx", proxied)):
                    t0 = time.perf_counter()
                    post(conn, path, batch)
                    times[name].append(time.perf_counter() - t0)
            for name in ("direct", "nginx"):
                s = times[name]
                print(f"{rays:>7} rays  {name:>6}: p50 {percentile(s, 50) * 1e6:8.1f} us  "
                      f"p99 {percentile(s, 99) * 1e6:8.1f} us  ({len(s)} requests)")
            add50 = percentile(times["nginx"], 50) - percentile(times["direct"], 50)
            add99 = percentile(times["nginx"], 99) - percentile(times["direct"], 99)
            print(f"{rays:>7} rays  nginx adds p50 {add50 * 1e6:+.1f} us, p99 {add99 * 1e6:+.1f} us")
        big = rays_body(1 << 20, 7)
        for conn in (direct, proxied):
            post(conn, path, big)
        times = {"direct": [], "nginx": []}
        for _ in range(args.reps):
            for name, conn in (("direct", direct), ("nginx", proxied)):
                t0 = time.perf_counter()
                post(conn, path, big)
                times[name].append(time.perf_counter() - t0)
        for name in ("direct", "nginx"):
            med = statistics.median(times[name])
            print(f"1M rays  {name:>6}: median {med * 1e3:8.1f} ms  {(1 << 20) / med / 1e6:6.2f} "
                  f"Mrays/s  ({args.reps} batches)")
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGQUIT if p is procs[-1] and len(procs) > 1 else signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
